"""Silhouettes (not in the paper; datasets with alpha masks): in every rendered view, the mean
distance from each particle's projection to the fluid's mask (``hull_distance``) plus the mean
distance from ``PIXELS`` random mask pixels to the nearest projection (``silhouette_coverage``).
The image loss reaches a particle only through the pixels it covers; this term reaches particles
and uncovered fluid at any distance, which large motions need."""

from __future__ import annotations

import torch

from .base import Term

PIXELS = 256  # fluid pixels per view and step for the coverage direction


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


def silhouette(ctx, i: int):
    """(distance to the silhouette (H, W), the fluid pixels' centres in a fixed random order with
    the first PIXELS repeated at the end (P + PIXELS, 2), P) of training image i, computed once.
    A step takes PIXELS consecutive rows from a random start: a slice, no host-to-device copy."""
    def make():
        a = ctx.views.alphas[i]
        rows, cols = torch.nonzero(a >= 0.5, as_tuple=True)
        pix = torch.stack([cols, rows], -1).to(a.dtype) + 0.5
        n = pix.shape[0]
        if n:
            order = torch.randperm(n, generator=torch.Generator().manual_seed(ctx.seed + i))
            pix = pix[order.to(pix.device)]
            pix = pix.repeat(-(-(n + PIXELS) // n), 1)[:n + PIXELS]
        return silhouette_distance(a), pix, n

    return ctx.memo(("silhouette", i), make)


class HullTerm(Term):
    def prepare(self, ctx, f, w):
        """Each masked image's first coverage pixel, drawn as its frame comes."""
        f.scratch["hull"] = []
        for i in f.images:
            if ctx.views.alphas[i] is not None:
                n_pix = silhouette(ctx, i)[2]
                f.scratch["hull"].append((i, f.means, int(ctx.rng.integers(n_pix)) if n_pix else 0))

    def step(self, ctx, s, w):
        """Sum over the step's images of hull_distance + silhouette_coverage, batched over the
        images of one size (two calls per size instead of two per image), over the images."""
        items = [it for f in s.frames for it in f.scratch.get("hull", ())]
        if not items:
            return None
        groups: dict = {}
        for item in items:
            cam = ctx.views.cameras[item[0]]
            groups.setdefault((cam.height, cam.width), []).append(item)
        total = 0.0
        for (_, width), grp in groups.items():
            means = torch.stack([m for _, m, _ in grp])
            cams = [ctx.camera_tensors(i) for i, _, _ in grp]
            vm, K = torch.stack([c[0] for c in cams]), torch.stack([c[1] for c in cams])
            sils = [silhouette(ctx, i) for i, _, _ in grp]
            total = total + hull_distance(means, torch.stack([sl[0] for sl in sils]), vm, K).sum()
            cov = [k for k, sl in enumerate(sils) if sl[2] > 0]  # an empty mask has no pixels to cover
            if cov:
                pix = torch.stack([sils[k][1][grp[k][2]:grp[k][2] + PIXELS] for k in cov])
                if len(cov) < len(grp):
                    means, vm, K = means[cov], vm[cov], K[cov]
                total = total + silhouette_coverage(means, pix, vm, K, width).sum()
        return w["hull"] * total / s.n_images


HULL = HullTerm("hull", (("hull", 1.0),), per="step")
