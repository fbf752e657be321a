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
from ..render.reference import quat_to_rotmat


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


def flow_error(recon: np.ndarray, recon_vel: np.ndarray, gt: np.ndarray, gt_vel: np.ndarray) -> dict:
    """How well the reconstructed particles move with the fluid where they are: the true flow at
    each reconstructed particle is the velocity of its nearest true particle. ``velocity_error``:
    mean |v - v_true there| (m/s); ``true_speed``: the root mean square of the true flow there;
    ``flow_following``: <v . v_true> / <|v_true|^2> over the particles (1: they move with the
    flow, 0: they stand still while it passes, or move across it). Total kinetic energy alone
    cannot tell a splash carried by its particles from one whose particles stand still while a
    few others jitter."""
    from scipy.spatial import cKDTree

    a, va = np.asarray(recon, np.float64), np.asarray(recon_vel, np.float64)
    b, vb = np.asarray(gt, np.float64), np.asarray(gt_vel, np.float64)
    if len(a) == 0 or len(b) == 0:
        return {"velocity_error": math.nan, "true_speed": math.nan, "flow_following": math.nan}
    _, j = cKDTree(b).query(a)
    vt = vb[j]
    sq = float((vt * vt).sum(1).mean())
    return {"velocity_error": float(np.linalg.norm(va - vt, axis=1).mean()), "true_speed": math.sqrt(sq),
            "flow_following": float((va * vt).sum(1).mean() / sq) if sq > 0 else math.nan}


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


def gaussian_cell_mean(means, scales, quats, opacities, domain_min, cell, shape, *, k: int = 32) -> np.ndarray:
    """The reconstruction's density averaged over each cell of a regular grid (``shape`` cells of
    size ``cell`` from ``domain_min``): the mean over the cell of sum_i o_i exp(-1/2 (x - mu_i)^T
    Sigma_i^-1 (x - mu_i)), the same cell averages a finite-volume grid holds. Sampling the sum at
    the cell centres instead would alias Gaussians smaller than a cell (a centre hits or misses
    them). Per Gaussian, the mean over a box is the product of its three marginals' (normal CDFs
    with the covariance's diagonal), exact for Gaussians aligned with the axes (isotropic ones
    included), times the ratio of the Gaussian widened by the box's own variance (Sigma' = Sigma +
    diag(cell^2 / 12)) to that widened Gaussian without its off-diagonal terms: the correction is 1
    for Gaussians small against a cell and turns the product into the widened Gaussian for large
    rotated ones. Every Gaussian's total o_i (2 pi)^(3/2) |Sigma_i|^(1/2) is kept.
    Each cell sums its ``k`` nearest particle centres (the rest lie several of their own standard
    deviations away when the Gaussians are no larger than their spacing). Returns ``shape``."""
    from scipy.spatial import cKDTree
    from scipy.special import ndtr

    shape = tuple(int(n) for n in shape)
    lo, c = np.asarray(domain_min, np.float64), np.asarray(cell, np.float64)
    mu = np.asarray(means, np.float64)
    if len(mu) == 0:
        return np.zeros(shape)
    s = np.asarray(scales, np.float64)
    R = quat_to_rotmat(torch.as_tensor(np.asarray(quats, np.float64))).numpy()
    cov = np.einsum("nij,nj,nkj->nik", R, s ** 2, R) + np.diag(c ** 2 / 12)   # Sigma' (N, 3, 3)
    var = np.einsum("nii->ni", cov)                                       # its diagonal D'
    sigma = np.sqrt(var - c ** 2 / 12)                                    # the marginals of Sigma itself
    # what the off-diagonal terms change: N(d; Sigma') / N(d; D') = sqrt(|D'| / |Sigma'|) exp(-1/2 d^T A d)
    A = np.linalg.inv(cov) - np.einsum("ni,ij->nij", 1 / var, np.eye(3))
    norm = np.sqrt(var.prod(1) / np.linalg.det(cov))
    amp = np.asarray(opacities, np.float64) * (2 * math.pi) ** 1.5 * s.prod(1) / c.prod()
    axes = [lo[a] + (np.arange(shape[a]) + 0.5) * c[a] for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    k = min(k, len(mu))
    tree = cKDTree(mu)
    out = np.empty(len(pts))
    for a in range(0, len(pts), 16384):  # bounded memory: (chunk, k, 3) at a time
        p = pts[a:a + 16384]
        _, idx = tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        d, sg = p[:, None, :] - mu[idx], sigma[idx]
        box = ndtr((d + c / 2) / sg) - ndtr((d - c / 2) / sg)            # (chunk, k, 3): each axis' share
        # in logs: far from a Gaussian the box's share underflows to 0 while the ratio (A is
        # indefinite) may overflow; the ratio is capped at e^30 and a zero share stays zero
        with np.errstate(divide="ignore"):
            log_box = np.log(box.prod(-1))
        log_rot = np.minimum(np.log(norm[idx]) - 0.5 * np.einsum("mki,mkij,mkj->mk", d, A[idx], d), 30.0)
        out[a:a + 16384] = (amp[idx] * np.exp(log_box + log_rot)).sum(-1)
    return out.reshape(shape)


def density_agreement(recon: list[np.ndarray], truth: list[np.ndarray]) -> dict:
    """A reconstructed density field against the true one, frame by frame: the Pearson correlation
    over the grid's cells, and the relative L2 error after one least-squares scale for the whole
    clip (the reconstruction's density has no unit of its own; one scale keeps how the amount of
    smoke changes over time in the comparison). Frames whose true field is empty are listed but not
    scored."""
    a = np.concatenate([np.ravel(r) for r in recon])
    b = np.concatenate([np.ravel(t) for t in truth])
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("density_agreement: a density field holds NaN or infinite values")
    scale = float(a @ b / max(a @ a, 1e-300))
    rows = []
    for r, t in zip(recon, truth):
        r, t = np.ravel(r), np.ravel(t)
        if not np.any(t > 0):  # no smoke yet: nothing to correlate with (the frame is left out of the scores)
            rows.append({"corr": None, "error": None, "empty_truth": True})
            continue
        corr = float(np.corrcoef(r, t)[0, 1]) if r.std() > 0 and t.std() > 0 else 0.0
        err = float(np.linalg.norm(scale * r - t) / np.linalg.norm(t))
        rows.append({"corr": corr, "error": err})
    scored = [x for x in rows if x["corr"] is not None]
    if not scored:
        return {"scale": scale, "per_frame": rows, "corr_mean": None, "corr_min_frame": None, "error_mean": None}
    return {"scale": scale, "per_frame": rows, "corr_mean": float(np.mean([x["corr"] for x in scored])),
            "corr_min_frame": float(min(x["corr"] for x in scored)),
            "error_mean": float(np.mean([x["error"] for x in scored]))}
