"""The loss terms of GaussFluids (paper Sec. 3.3, Eqs. 5-11), one function per equation.

Every function takes plain tensors and returns a scalar tensor; the trainer weights and sums
them (Eq. 11) and never calls a term whose weight is 0.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F

# Table 1 of the paper: the final weights of Eq. 11
TABLE1_WEIGHTS = {"rgb": 0.2, "ssim": 0.1, "density": 0.1, "aniso": 0.1, "volume": 0.1,
                  "opacity": 0.01, "color": 1.0}


# ---- visual consistency (3DGS, Kerbl et al. 2023) --------------------------------------------------
def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_rgb: mean absolute error (of a batch of same-size images: the mean of their L_rgb)."""
    return (pred - target).abs().mean()


@lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float, dtype, device_str: str) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).to(dtype=dtype, device=torch.device(device_str))


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, C, H, W), 'valid' borders (as 3DGS's SSIM with padding)."""
    c = x.shape[1]
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c, padding=(0, k // 2))
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c, padding=(k // 2, 0))


def _nchw(img: torch.Tensor) -> torch.Tensor:
    """(H, W, C) or a batch (B, H, W, C) -> (B, C, H, W)."""
    return img.permute(2, 0, 1)[None] if img.dim() == 3 else img.permute(0, 3, 1, 2)


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W, C) image, or a batch (B, H, W, C), blurred with a Gaussian of ``sigma`` pixels
    (separable, zero padding)."""
    size = 2 * int(math.ceil(3 * sigma)) + 1
    x = _nchw(img)
    g = _gauss_1d(size, float(sigma), x.dtype, str(x.device))
    y = _blur(x, g).permute(0, 2, 3, 1)
    return y[0] if img.dim() == 3 else y


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) of (H, W, C) images in [0, 1] with an 11x11 Gaussian window
    (sigma 1.5), zero padding as in 3DGS. Separable filtering: 2 x 11 taps per pixel, not 121.
    A batch (B, H, W, C) of same-size images gives the mean of their SSIMs."""
    x, y = _nchw(pred), _nchw(target)
    g = _gauss_1d(window, sigma, x.dtype, str(x.device))
    both = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g)
    c = x.shape[1]
    mu_x, mu_y, xx, yy, xy = both.split(c, 1)
    sx, sy, sxy = xx - mu_x ** 2, yy - mu_y ** 2, xy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sx + sy + c2))
    return s.mean()


def d_ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_d-ssim = 1 - SSIM."""
    return 1.0 - ssim(pred, target)


# ---- physics: SPH density uniformity (Eqs. 5, 6) --------------------------------------------------
def poly6(r2: torch.Tensor, h: float) -> torch.Tensor:
    """Poly6 kernel (Eq. 6, Mueller et al. 2003) of the squared distance: 315/(64 pi h^9) (h^2-r^2)^3
    inside the support, 0 outside."""
    return (315.0 / (64.0 * math.pi * h ** 9)) * torch.clamp_min(h * h - r2, 0.0) ** 3


def sph_density(positions: torch.Tensor, nbr_i: torch.Tensor, nbr_j: torch.Tensor, h: float) -> torch.Tensor:
    """D_i = sum_j W(|p_i - p_j|, h) with unit mass (Eq. 5), self term included, over stored
    neighbour pairs (i, j), i != j. Gradients flow through the pair distances; a pair that has
    moved beyond h since the list was built contributes 0 (the kernel's support)."""
    d = positions[nbr_i] - positions[nbr_j]
    w = poly6((d * d).sum(-1), h)
    w0 = 315.0 / (64.0 * math.pi * h ** 3)  # W(0) = 315 h^6 / (64 pi h^9)
    dens = torch.full((positions.shape[0],), w0, dtype=positions.dtype, device=positions.device)
    return dens.index_add(0, nbr_i, w)


def sph_density_knn(positions: torch.Tensor, idx: torch.Tensor, h: float) -> torch.Tensor:
    """``sph_density`` over (N, K) neighbour indices (-1 = none, as ``neighbors.knn`` returns):
    one native call (C++ or CUDA, hand-written backward) where the extension is built, else the
    pair form above."""
    from .render import native

    dev = positions.device.type
    if native.available() and (dev == "cpu" or (dev == "cuda" and native.has_cuda())):
        return native.DensityFn.apply(positions.contiguous(), idx.contiguous(), h)
    rows = torch.arange(positions.shape[0], device=positions.device)[:, None].expand_as(idx)
    ok = idx >= 0
    return sph_density(positions, rows[ok], idx[ok], h)


def density_uniformity(density: torch.Tensor) -> torch.Tensor:
    """L_dens = mean_i (D_i / mean(D) - 1)^2 (Eq. 5)."""
    return ((density / density.mean().clamp_min(1e-30) - 1.0) ** 2).mean()


# ---- geometry (Eqs. 7, 8) -------------------------------------------------------------------------
def volume_consistency(scales: torch.Tensor) -> torch.Tensor:
    """L_vol = mean_i (V_i / mean(V) - 1)^2 with V_i = s_x s_y s_z (Eq. 7)."""
    v = scales.prod(-1)
    return ((v / v.mean().clamp_min(1e-30) - 1.0) ** 2).mean()


def anisotropy(scales: torch.Tensor) -> torch.Tensor:
    """L_aniso = mean_i || s_i / V_i^(1/3) - (1, 1, 1) ||^2 (Eq. 8). V_i^(1/3) is evaluated as the
    geometric mean exp(mean(log s)), which is the same number without the cube root of a product
    that underflows for tiny particles."""
    geo = torch.exp(torch.log(scales.clamp_min(1e-30)).mean(-1, keepdim=True))
    return ((scales / geo - 1.0) ** 2).sum(-1).mean()


# ---- appearance consistency (Eqs. 9, 10) ----------------------------------------------------------
def mse_to_mean(y: torch.Tensor) -> torch.Tensor:
    """L_MSE(y) = mean_i ||y_i - mean(y)||^2 (Eq. 10); y is (N,) or (N, ...)."""
    y = y.reshape(y.shape[0], -1)
    return ((y - y.mean(0, keepdim=True)) ** 2).sum(-1).mean()


def opacity_consistency(opacities: torch.Tensor) -> torch.Tensor:
    """L_op = L_MSE(alpha) (Eq. 9)."""
    return mse_to_mean(opacities)


def color_consistency(sh: torch.Tensor) -> torch.Tensor:
    """L_light = L_MSE(c) over the SH coefficients (Eq. 9)."""
    return mse_to_mean(sh)


# ---- silhouettes (alpha masks; not in the paper) -------------------------------------------------
def silhouette_distance(alpha: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """(H, W) distance from each pixel to the nearest pixel of the fluid (alpha >= threshold), in
    units of the image width; 0 on the fluid. Computed once per training image."""
    import cv2
    import numpy as np

    a = alpha.detach().cpu().numpy()
    outside = (a < threshold).astype(np.uint8)
    if outside.all():  # an empty mask: no pull anywhere
        return torch.zeros_like(alpha)
    d = cv2.distanceTransform(outside, cv2.DIST_L2, 5)
    return torch.as_tensor(d / a.shape[1], dtype=alpha.dtype, device=alpha.device)


def least_motion(positions: list, taus: list, spacing: float) -> torch.Tensor:
    """Not in the paper: sum over consecutive decoded times of mean_i |p_i(b) - p_i(a)|^2 /
    (spacing^2 |tau_b - tau_a|), a discrete integral of the squared speed (kinetic action) in
    particle spacings per normalised time. Rendering cannot tell which particle is which inside
    the fluid, so particles may circulate without changing an image; this prefers the quietest
    motion that explains the images. ``positions`` (T, N, 3) in the order of ``taus``."""
    order = sorted(range(len(taus)), key=lambda k: taus[k])
    total = positions[0].new_zeros(())
    for a, b in zip(order, order[1:]):
        dt = abs(taus[b] - taus[a])
        if dt > 1e-9:
            total = total + ((positions[b] - positions[a]) ** 2).sum(-1).mean() / (spacing ** 2 * dt)
    return total


def acceleration(dp_prev: torch.Tensor, dp: torch.Tensor, dp_next: torch.Tensor, h0: float, h1: float,
                 frame: float, spacing: float) -> torch.Tensor:
    """Not in the paper: mean_i |a_i|^2 of each particle's acceleration at a training frame, from
    its positions at that frame and its two neighbours (the non-uniform second difference, taus
    h0 before and h1 after), in particle spacings per frame^2 (``frame``: the mean knot step in
    tau):

        a_i = 2 [h0 (p_i(+) - p_i) - h1 (p_i - p_i(-))] / (h0 h1 (h0 + h1)) * frame^2 / spacing

    The images cannot tell which particle is which, so per-frame corrections may let particles
    jump about between frames without changing an image; this prefers motion whose velocity
    changes smoothly, as a fluid's does. ``dp_*`` (N, 3): positions, or anything that differs from
    them by the same offset at the three times (the canonical positions cancel)."""
    a = 2.0 * (h0 * (dp_next - dp) - h1 * (dp - dp_prev)) / (h0 * h1 * (h0 + h1)) * (frame ** 2 / spacing)
    return (a * a).sum(-1).mean()


def residual_change(r: torch.Tensor, r_nbrs: torch.Tensor, spacing: float) -> torch.Tensor:
    """Not in the paper: mean_i of |R_i(k) - R_i(k')|^2 / spacing^2 over the neighbouring training
    frames k' of frame k (the mean over them), in particle spacings per frame. The position
    residuals R are fitted frame by frame, and the images cannot tell which particle is which
    inside the fluid, so without this term the particles may trade places from one frame to the
    next while every frame's image stays right; their velocities (and the kinetic energy, motion
    blur, predictions that use them) then measure that shuffle, not the flow. With a frozen decoder
    carrying the bulk motion, this penalises only the motion the residuals add.
    ``r`` (N, 3): the residual at frame k; ``r_nbrs`` (N, M, 3) at its M neighbours."""
    d = r_nbrs - r[:, None, :]
    return (d * d).sum(-1).mean() / (spacing * spacing)


def _to_camera(means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """(I, N, 3) world points in each of I cameras (I, 4, 4): (I, N, 3) camera coordinates."""
    return means @ viewmat[:, :3, :3].transpose(1, 2) + viewmat[:, None, :3, 3]


def hull_distance(means: torch.Tensor, dist: torch.Tensor, viewmat: torch.Tensor, intr: torch.Tensor) -> torch.Tensor:
    """Mean over particles of the silhouette distance (``silhouette_distance``) at each particle's
    projection: a pull towards the fluid's silhouette that reaches particles far outside it (the
    image loss only reaches a particle through pixels it covers). Particles behind the camera add 0.

    One image: means (N, 3), dist (H, W), viewmat (4, 4), intr (4,) -> a scalar. A batch of I
    images of one size (one call instead of I): means (I, N, 3), dist (I, H, W), viewmat
    (I, 4, 4), intr (I, 4) -> (I,), one value per image."""
    single = means.dim() == 2
    if single:
        means, dist, viewmat, intr = means[None], dist[None], viewmat[None], intr[None]
    t = _to_camera(means, viewmat)
    z = t[..., 2]
    front = z > 1e-6
    zs = torch.where(front, z, torch.ones_like(z))
    u = intr[:, 0:1] * t[..., 0] / zs + intr[:, 2:3]
    v = intr[:, 1:2] * t[..., 1] / zs + intr[:, 3:4]
    H, W = dist.shape[-2:]
    grid = torch.stack([2 * u / W - 1, 2 * v / H - 1], -1)[:, None]  # (I, 1, N, 2); pixel edges at +-1
    d = torch.nn.functional.grid_sample(dist[:, None], grid, mode="bilinear", padding_mode="border",
                                        align_corners=False)[:, 0, 0]
    out = torch.where(front, d, torch.zeros_like(d)).mean(-1)
    return out[0] if single else out


def silhouette_coverage(means: torch.Tensor, pixels: torch.Tensor, viewmat: torch.Tensor, intr: torch.Tensor,
                        width: int) -> torch.Tensor:
    """The other direction: mean over fluid pixels ``pixels`` (P, 2) (u, v centres; a random subset
    of the mask) of the distance (x image width) to the nearest particle's projection. It pulls the
    nearest particles into parts of the silhouette that no particle covers (a spreading pool's
    rim, a splash). Batched like ``hull_distance``: means (I, N, 3), pixels (I, P, 2), viewmat
    (I, 4, 4), intr (I, 4) -> (I,)."""
    single = means.dim() == 2
    if single:
        means, pixels, viewmat, intr = means[None], pixels[None], viewmat[None], intr[None]
    if pixels.shape[1] == 0 or means.shape[1] == 0:
        out = means.sum((1, 2)) * 0.0
        return out[0] if single else out
    t = _to_camera(means, viewmat)
    z = t[..., 2].clamp_min(1e-6)
    uv = torch.stack([intr[:, 0:1] * t[..., 0] / z + intr[:, 2:3], intr[:, 1:2] * t[..., 1] / z + intr[:, 3:4]], -1)
    uv = torch.where((t[..., 2] > 1e-6)[..., None], uv, torch.full_like(uv, 1e9))
    pixels = pixels.to(uv.dtype)
    with torch.no_grad():  # which projection is nearest: no gradient through the (I, P, N) distances
        j = torch.cdist(pixels, uv).argmin(-1)  # (I, P)
    d = (pixels - torch.gather(uv, 1, j[..., None].expand(-1, -1, 2))).norm(dim=-1)  # (I, P), the min's value and gradient
    out = d.mean(-1) / width
    return out[0] if single else out


def floor_coverage(means: torch.Tensor, samples: torch.Tensor, spacing: float) -> torch.Tensor:
    """Not in the paper: mean over floor points ``samples`` (M, 3) of the distance, in particle
    spacings, to the nearest particle of ``means`` (N, 3), beyond one spacing (a sheet's particles
    lie within about half a spacing of the floor points; only holes pull). The samples are the points of the scene
    box's floor that every training view of the frame sees inside the fluid's silhouette (see
    ``Trainer._floor_samples``): there the fluid rests on the floor. Views that look down at a
    spreading sheet cannot tell it from fluid held higher up along their rays (a mound over the
    middle, with the far side of the tank left empty); this pulls the nearest particles onto the
    floor where the silhouettes say the sheet is. The nearest particle is found without gradient,
    the distance to it carries it."""
    if samples.shape[0] == 0 or means.shape[0] == 0:
        return means.sum() * 0.0
    with torch.no_grad():
        j = torch.cdist(samples, means.detach()).argmin(-1)
    return torch.relu((samples - means[j]).norm(dim=-1) / spacing - 1.0).mean()


@torch.no_grad()
def unsupported(positions: torch.Tensor, idx: torch.Tensor, spacing: float, floor: float) -> torch.Tensor:
    """(N,) bool: particles (N, 3) with no neighbour (``idx`` (N, K), -1 = none, as
    ``neighbors.knn`` returns) below them within a 45-degree cone at least half a spacing lower,
    and more than one spacing above ``floor`` (gravity along -z): fluid held up by nothing."""
    z = positions[:, 2]
    ok = idx >= 0
    q = positions[idx.clamp_min(0)]  # (N, K, 3)
    dz = z[:, None] - q[..., 2]
    dh = (positions[:, None, :2] - q[..., :2]).norm(dim=-1)
    below = ok & (dz > 0.5 * spacing) & (dh < dz)
    return ~below.any(1) & (z > floor + spacing)


def settling(positions: torch.Tensor, gate: torch.Tensor, floor: float, spacing: float) -> torch.Tensor:
    """Not in the paper: potential energy of the ``gate``d particles (N,) bool, their height above
    ``floor`` in particle spacings summed over them and divided by all N (gravity along -z). The
    trainer gates it to fluid that hangs unsupported (``unsupported``) over a wet floor (where
    ``floor_coverage``'s points say the fluid rests on the floor): views looking down at a sheet
    cannot tell it from fluid held higher along their rays, but fluid cannot hover over a pool."""
    height = (positions[:, 2] - floor) / spacing
    return torch.where(gate, height, torch.zeros_like(height)).mean()


# ---- metrics shared with evaluation ---------------------------------------------------------------
def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    mse = float(((pred.detach() - target.detach()) ** 2).mean())
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


__all__ = ["acceleration", "TABLE1_WEIGHTS", "l1", "blur", "ssim", "d_ssim", "poly6", "sph_density", "sph_density_knn", "density_uniformity",
           "volume_consistency", "anisotropy", "mse_to_mean", "opacity_consistency", "color_consistency",
           "silhouette_distance", "least_motion", "hull_distance", "silhouette_coverage", "floor_coverage", "unsupported", "settling", "psnr"]
