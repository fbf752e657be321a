"""The differentiable Gaussian-particle renderer: one public entry, ``render``.

Backends: ``reference`` (pure torch, any device, autograd: the oracle) and ``native`` (one
extension: C++/OpenMP for CPU tensors, CUDA for GPU tensors, hand-written backward).
``backend="auto"`` picks native whenever it is built for the tensors' device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..camera import Camera
from ..errors import InputError
from . import native, reference
from .constants import DEFAULT_MIN_ALPHA, TILE_SIZE, TILE_SIZE_CUDA

BACKENDS = ("auto", "reference", "native")


@dataclass
class RenderOutput:
    """color (H, W, C); alpha (H, W); depth (H, W) expected depth or None if not requested;
    means2d (N, 2) pixel positions, kept in the graph with ``retain_grad`` so that after
    ``backward()`` ``means2d.grad`` is the per-particle 2D mean gradient (densification);
    radii (N,) int32 splat radii in pixels, 0 for particles not drawn."""

    color: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None
    means2d: torch.Tensor
    radii: torch.Tensor
    backend: str

    @property
    def visible(self) -> torch.Tensor:
        return self.radii > 0


def _check(name, t, shape_tail, n=None):
    if not isinstance(t, torch.Tensor):
        raise InputError("render", f"{name} must be a torch tensor, got {type(t).__name__}")
    if t.dim() != 1 + len(shape_tail) or tuple(t.shape[1:]) != tuple(shape_tail) or (n is not None and t.shape[0] != n):
        want = ", ".join(["N"] + [str(s) for s in shape_tail])
        raise InputError("render", f"{name} must have shape ({want}) with N={n}, got {tuple(t.shape)}")


def _check_values(named: dict) -> None:
    """Finite values, non-negative scales, opacities in [0, 1]: one device sync for all checks."""
    scales, opac = named["scales"], named["opacities"]
    flags = [~torch.isfinite(t).all() for t in named.values()]
    flags += [(scales < 0).any(), ((opac < 0) | (opac > 1)).any()]
    bad = torch.stack(flags).cpu().tolist()
    for (name, _), b in zip(named.items(), bad):
        if b:
            raise InputError("render", f"{name} contains NaN or infinite values")
    if bad[-2]:
        raise InputError("render", "scales must be non-negative (pass exp(log_scales))")
    if bad[-1]:
        raise InputError("render", "opacities must lie in [0, 1] (pass sigmoid(logits))")


def _check_dtypes(named: dict) -> None:
    first, t0 = next(iter(named.items()))
    for name, t in named.items():
        if t.dtype not in (torch.float32, torch.float64):
            raise InputError("render", f"{name} is {t.dtype}; the renderer takes float32 or float64 tensors")
        if t.dtype != t0.dtype:
            raise InputError("render", f"{name} is {t.dtype} but {first} is {t0.dtype}; pass every tensor in one dtype")
        if t.device != t0.device:
            raise InputError("render", f"{name} is on {t.device} but {first} is on {t0.device}")


def _native_camera(camera: Camera):
    """(viewmat, intrinsics) as the CPU float64 tensors the native ops read, made once per camera
    (cameras are frozen) and kept on it: a render then builds no tensor for its camera."""
    cached = camera.__dict__.get("_native_tensors")
    if cached is None:
        cached = camera.to_torch(device="cpu", dtype=torch.float64)
        object.__setattr__(camera, "_native_tensors", cached)
    return cached


def pick_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown renderer backend {backend!r}; choose from {', '.join(BACKENDS)}")
    if backend == "auto":
        if device.type == "cpu":
            return "native" if native.available() else "reference"
        return "native" if device.type == "cuda" and native.has_cuda() else "reference"
    if backend == "native":
        if not native.available():
            raise RuntimeError(f"native backend unavailable: {native.unavailable_reason()}")
        if device.type == "cuda" and not native.has_cuda():
            raise ValueError("the native extension was built without CUDA (no nvcc, or no GPU at build time); "
                             "use backend='reference' for CUDA tensors")
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"the native backend runs on CPU and CUDA tensors, not {device.type}")
    return backend


def render(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor, opacities: torch.Tensor,
           sh: torch.Tensor, camera: Camera, background=None, *, sh_degree: int | None = None,
           backend: str = "auto", min_alpha: float = DEFAULT_MIN_ALPHA, return_depth: bool = False,
           tile_size: int | None = None) -> RenderOutput:
    """Splat Gaussian particles into ``camera`` (paper Eq. 3).

    means (N, 3) world positions; scales (N, 3) > 0 (activated); quats (N, 4) w, x, y, z, any norm;
    opacities (N,) in [0, 1] (activated); sh (N, K, C) SH coefficients, K = (degree+1)^2 >= 1,
    C = 1 (grayscale) or 3. ``background`` (C,) defaults to black. ``min_alpha``: a splat whose
    alpha at a pixel is below this is skipped there (default 1e-3, far below a 1%-opacity
    particle's centre). Depth is composited only when ``return_depth``. ``tile_size`` (pixels per
    tile side; the image does not depend on it) defaults to 8 for the native backend on CUDA, else 16.
    """
    n = means.shape[0] if isinstance(means, torch.Tensor) and means.dim() == 2 else None
    _check("means", means, (3,))
    _check("scales", scales, (3,), n)
    _check("quats", quats, (4,), n)
    _check("opacities", opacities, (), n)
    if not isinstance(sh, torch.Tensor) or sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] not in (1, 3) \
            or sh.shape[1] not in (1, 4, 9, 16):
        raise InputError("render", f"sh must have shape (N={n}, (degree+1)^2, 1 or 3), got "
                                   f"{tuple(sh.shape) if isinstance(sh, torch.Tensor) else type(sh).__name__}")
    named = {"means": means, "scales": scales, "quats": quats, "opacities": opacities, "sh": sh}
    _check_dtypes(named)
    if not 0 < min_alpha < 1:
        raise ValueError(f"min_alpha must be in (0, 1), got {min_alpha}")
    max_degree = int(math.isqrt(sh.shape[1])) - 1
    degree = max_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= max_degree:
        raise ValueError(f"sh_degree {degree} needs {(degree + 1) ** 2} coefficients, sh has {sh.shape[1]}")
    dev, dt = means.device, means.dtype
    channels = sh.shape[2]
    bg = torch.zeros(channels, dtype=dt, device=dev) if background is None else \
        torch.as_tensor(background, dtype=dt, device=dev).reshape(-1)
    if bg.numel() != channels:
        raise InputError("render", f"background has {bg.numel()} values for {channels} channels")
    W, H = camera.width, camera.height
    which = pick_backend(backend, dev)
    if tile_size is None:
        tile_size = TILE_SIZE_CUDA if which == "native" and dev.type == "cuda" else TILE_SIZE
    if which != "native":  # the native projection checks every value itself, in the same pass
        _check_values(named)
    viewmat, intr = _native_camera(camera) if which == "native" else camera.to_torch(device=dev, dtype=torch.float64)

    if which == "native":
        means2d, conics, depths, colors, radii = native.ProjectFn.apply(
            means, scales, quats, opacities, sh, viewmat, intr, W, H, camera.near,
            min_alpha, degree)
    else:
        means2d, conics, depths, colors, radii = reference.project(
            means, scales, quats, opacities, sh, viewmat, intr, W, H, near=camera.near,
            min_alpha=min_alpha, sh_degree=degree)
    if means2d.requires_grad:
        means2d.retain_grad()
    features = torch.cat([colors, depths[:, None]], 1) if return_depth else colors
    bg_f = torch.cat([bg, bg.new_zeros(1)]) if return_depth else bg
    if which == "native":
        try:
            img, T = native.RasterizeFn.apply(means2d, conics, opacities, features, bg_f, radii, depths,
                                              W, H, tile_size, min_alpha)
        except native.InvalidInput:
            _check_values(named)  # names the tensor and the problem
            raise
    else:
        img, T = reference.rasterize(means2d, conics, opacities, features, bg_f, radii, depths, W, H,
                                     tile=tile_size, min_alpha=min_alpha)
    alpha = 1.0 - T
    depth = None
    if return_depth:
        depth = img[..., channels] / torch.clamp_min(alpha, 1e-6)
        img = img[..., :channels]
    return RenderOutput(color=img, alpha=alpha, depth=depth, means2d=means2d, radii=radii, backend=which)


def render_points(positions, camera: Camera, *, radius: float, color=(0.5, 0.7, 1.0), opacity: float = 0.5,
                  background=None, channels: int = 3, dtype=torch.float32, device=None) -> RenderOutput:
    """Points drawn as isotropic Gaussians of std ``radius``, one colour and opacity (what the tests'
    synthetic datasets and the demo's dot pictures show); SH degree 1 with only its base colour."""
    import numpy as np

    from .constants import SH_C0

    p = torch.as_tensor(np.asarray(positions), dtype=dtype, device=device).reshape(-1, 3)
    n = p.shape[0]
    if not 0 < opacity < 1:
        raise ValueError(f"opacity must be in (0, 1), got {opacity}")
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    col = torch.as_tensor(color, dtype=dtype, device=device).reshape(-1)[:channels]
    sh = torch.zeros(n, 4, channels, dtype=dtype, device=device)
    sh[:, 0, :] = (col - 0.5) / SH_C0  # colour = SH_C0 * sh0 + 0.5
    quats = torch.zeros(n, 4, dtype=dtype, device=device)
    quats[:, 0] = 1
    scales = torch.exp(torch.full((n, 3), math.log(radius), dtype=dtype, device=device))
    opacities = torch.sigmoid(torch.full((n,), math.log(opacity / (1 - opacity)), dtype=dtype, device=device))
    return render(p, scales, quats, opacities, sh, camera, background)


__all__ = ["render", "render_points", "RenderOutput", "BACKENDS", "DEFAULT_MIN_ALPHA"]
