"""Constants shared by every renderer backend (the C++/CUDA header repeats them; a test checks)."""

LOW_PASS = 0.3            # added to the 2D covariance diagonal (EWA low-pass filter, 3DGS)
ALPHA_MAX = 0.99          # per-splat alpha clamp (3DGS)
TRANSMITTANCE_MIN = 1e-4  # a pixel stops compositing once its transmittance would drop below this
FRUSTUM_SLACK = 1.3       # x/z and y/z are clamped to 1.3x the image extent in the EWA Jacobian
DEFAULT_MIN_ALPHA = 1e-3  # splats with alpha below this at a pixel are skipped there
TILE_SIZE = 16            # pixels per tile side, CPU backends
TILE_SIZE_CUDA = 8        # CUDA: 4x the blocks on a crowded image (BENCHMARKS.md, CUDA backend)

# Real spherical harmonics (as in 3DGS), degree 0..3.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
