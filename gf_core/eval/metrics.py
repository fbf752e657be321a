"""Measures of a reconstruction: image fidelity (PSNR, SSIM), the SPH density spread (paper
Fig. 4), and particle error against ground-truth particles (nearest-neighbour distances in
both directions, in units of the true particle spacing).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..recon.terms.aniso import anisotropy
from ..recon.terms.image import psnr, ssim
from ..recon.terms.volume import volume_consistency
from ..sph.density import particle_volume, sph_density_knn  # noqa: F401 - particle_volume: a measure of this module too
from ..sph.kernels import poly6
from ..sph.neighbors import knn


def image_metrics(pred: torch.Tensor, target: torch.Tensor) -> dict:
    return {"psnr": psnr(pred, target), "ssim": float(ssim(pred.detach(), target.detach()))}


def nearest_distance(a: torch.Tensor, b: torch.Tensor, radius: float) -> torch.Tensor:
    """For each point of ``a`` (N, 3), the distance to the nearest point of ``b`` (M, 3), through the
    grid search with a radius that doubles for the points still without a neighbour."""
    a = a.detach().double()
    b = b.detach().double()
    out = torch.full((a.shape[0],), math.inf, dtype=torch.float64, device=a.device)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return out
    todo = torch.arange(a.shape[0], device=a.device)
    r = float(radius)
    span = float((torch.cat([a, b]).max(0).values - torch.cat([a, b]).min(0).values).norm()) + 1e-9
    while todo.numel():
        if r > 2 * span or todo.numel() * b.shape[0] <= 4_000_000:
            # few left, or a radius as large as the data: direct, in chunks of bounded memory
            for s in range(0, todo.numel(), 4096):
                ids = todo[s:s + 4096]
                out[ids] = torch.cdist(a[ids], b).min(1).values
            break
        _, dist = knn(a[todo], 1, r, b)
        found = torch.isfinite(dist[:, 0])
        out[todo[found]] = dist[found, 0]
        todo = todo[~found]
        r *= 2
    return out


def particle_error(recon: np.ndarray, gt: np.ndarray, spacing: float) -> dict:
    """Both Chamfer directions in true particle spacings: ``gt_to_recon`` (is every true particle
    covered? the interior must be filled) and ``recon_to_gt`` (is every reconstructed particle
    on the fluid?), their means, 90th percentiles, and the fraction within one spacing."""
    a = torch.as_tensor(np.asarray(recon, np.float64))
    b = torch.as_tensor(np.asarray(gt, np.float64))
    g2r = nearest_distance(b, a, spacing) / spacing
    r2g = nearest_distance(a, b, spacing) / spacing
    out = {"particles_recon": int(a.shape[0]), "particles_gt": int(b.shape[0])}
    for name, d in (("gt_to_recon", g2r), ("recon_to_gt", r2g)):
        d = d.numpy()
        out[name] = float(d.mean()) if d.size else math.inf
        out[name + "_p90"] = float(np.percentile(d, 90)) if d.size else math.inf
        out[name + "_within_1"] = float((d <= 1.0).mean()) if d.size else 0.0
    out["chamfer"] = 0.5 * (out["gt_to_recon"] + out["recon_to_gt"])
    return out


def density_spread(positions: torch.Tensor, h: float, k: int = 64) -> dict:
    """The per-particle SPH density D_i (Eq. 5: Poly6, unit mass, up to K neighbours within h),
    normalised by its mean: its standard deviation (paper Fig. 4), and the raw mean."""
    x = positions.detach()
    if x.shape[0] == 0:
        return {"std": math.nan, "mean": math.nan}
    idx, _ = knn(x, k, h, sorted=False)
    d = sph_density_knn(x, idx, h)
    rel = d / d.mean()
    return {"std": float(rel.std(unbiased=False)), "mean": float(d.mean()),
            "self_only_fraction": float((d <= float(poly6(torch.zeros(()), h)) * (1 + 1e-6)).float().mean())}


def shape_spread(scales: torch.Tensor) -> dict:
    """How far the particles are from equal, round ones (what Eqs. 7 and 8 ask for): the paper's
    volume consistency L_vol and anisotropy L_aniso of the scales (N, 3), and the median and 95th
    percentile of each particle's longest / shortest axis."""
    s = scales.detach().double()
    if s.shape[0] == 0:
        return {"volume": math.nan, "aniso": math.nan, "axis_ratio_median": math.nan, "axis_ratio_p95": math.nan}
    ratio = s.max(-1).values / s.min(-1).values.clamp_min(1e-30)
    return {"volume": float(volume_consistency(s)), "aniso": float(anisotropy(s)),
            "axis_ratio_median": float(ratio.median()), "axis_ratio_p95": float(torch.quantile(ratio, 0.95))}


def mechanical_energy(positions, velocities, mass, z_ref: float, g: float = 9.81) -> dict:
    """Kinetic sum(m |v|^2 / 2), gravitational potential sum(m g (z - z_ref)) and their sum, in
    joules (paper Fig. 5); ``mass`` per particle (scalar or (N,)); gravity along -z."""
    p = np.asarray(positions, np.float64)
    v = np.asarray(velocities, np.float64)
    m = np.broadcast_to(np.asarray(mass, np.float64), (len(p),))
    kin = float(0.5 * (m * (v * v).sum(1)).sum())
    pot = float((m * g * (p[:, 2] - z_ref)).sum())
    return {"kinetic": kin, "potential": pot, "total": kin + pot}


def transport_distance(a, b, spacing: float, *, samples: int = 1000, seed: int = 0) -> dict:
    """Earth mover's distance between two particle sets, in ``spacing`` units: the mean distance of
    an optimal one-to-one matching (exact, scipy's linear_sum_assignment) between equal-size random
    subsamples of at most ``samples`` particles each (the matching is O(n^3))."""
    from scipy.optimize import linear_sum_assignment

    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    n = min(samples, len(a), len(b))
    if n == 0:
        return {"emd": math.inf, "emd_samples": 0}
    rng = np.random.default_rng(seed)
    sa = a[rng.choice(len(a), n, replace=False)]
    sb = b[rng.choice(len(b), n, replace=False)]
    cost = np.sqrt(((sa[:, None, :] - sb[None, :, :]) ** 2).sum(-1))
    rows, cols = linear_sum_assignment(cost)
    return {"emd": float(cost[rows, cols].mean() / spacing), "emd_samples": int(n)}


__all__ = ["image_metrics", "nearest_distance", "particle_error", "density_spread", "particle_volume",
           "mechanical_energy", "transport_distance"]
