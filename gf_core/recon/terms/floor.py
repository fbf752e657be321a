"""A fluid on the floor (not in the paper; alpha masks and a known floor, gravity along -z): views
that look down at a spreading sheet cannot tell it from fluid held higher up along their rays, and
the particles of a splash stay in a mound over the middle of the tank while the far side stays
empty. The floor points that every view of a frame sees inside the fluid (``floor_points``) mark
where the fluid rests on the floor; this term pulls the nearest particle into any of them left
without one. ``settle.py`` uses the same points."""

from __future__ import annotations

import numpy as np
import torch

from ..initial import in_hull
from .base import Term

SAMPLES = 256  # floor points per decoded time and step


def floor_coverage(means: torch.Tensor, samples: torch.Tensor, spacing: float) -> torch.Tensor:
    """Mean over floor points ``samples`` (M, 3) of the distance, in particle spacings, to the
    nearest particle of ``means`` (N, 3), beyond one spacing (a sheet's particles lie within about
    half a spacing of the floor points; only holes pull). The nearest particle is found without
    gradient, the distance to it carries it."""
    if samples.shape[0] == 0 or means.shape[0] == 0:
        return means.sum() * 0.0
    with torch.no_grad():
        j = torch.cdist(samples, means.detach()).argmin(-1)
    return torch.relu((samples - means[j]).norm(dim=-1) / spacing - 1.0).mean()


def floor_points(ctx, t: float):
    """The wet floor of training time ``t``, computed once: (its points in a fixed random order,
    the first SAMPLES repeated at the end (P + SAMPLES, 3), P, the (nx, ny) bool grid of the floor
    cells that hold one), or None. The points: a grid at the particle spacing on the scene box's
    floor (lowest z), half a spacing up, kept where every training view of that time that sees
    the point sees fluid (the alpha masks at model.carve_threshold). None where the frame's fluid
    does not reach the floor in every view (a falling drop) or a view has no alpha."""
    def make():
        views = ctx.views
        idx = views.at_time(t)
        if not idx or any(views.alphas[i] is None for i in idx):
            return None
        lo, hi, g = np.asarray(ctx.model.bounds.lo), np.asarray(ctx.model.bounds.hi), ctx.spacing
        nx, ny = int(np.ceil((hi[0] - lo[0]) / g)), int(np.ceil((hi[1] - lo[1]) / g))
        I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        P = np.stack([lo[0] + (I.ravel() + 0.5) * g, lo[1] + (J.ravel() + 0.5) * g, np.full(I.size, lo[2] + 0.5 * g)], 1)
        keep = in_hull(P, [(views.cameras[i], views.alphas[i]) for i in idx], ctx.cfg.model.carve_threshold)
        n = int(keep.sum())
        if not n:
            return None
        order = np.random.default_rng(ctx.seed).permutation(n)
        pts = P[keep][order]
        pts = np.concatenate([pts] * -(-(n + SAMPLES) // n))[:n + SAMPLES]
        wet = torch.as_tensor(keep.reshape(nx, ny), device=ctx.device)
        return torch.as_tensor(pts, dtype=torch.float32, device=ctx.device), n, wet

    return ctx.memo(("floor", t), make)


def floor_samples(ctx, t: float) -> torch.Tensor | None:
    """(M, 3) floor points of training time ``t``: all of them, or SAMPLES consecutive ones of the
    fixed random order from a random start (a slice, no host-to-device copy); None without a wet
    floor."""
    ent = floor_points(ctx, t)
    if ent is None:
        return None
    pts, n, _ = ent
    if n <= SAMPLES:
        return pts[:n]
    s = int(ctx.rng.integers(n))
    return pts[s:s + SAMPLES]


class FloorTerm(Term):
    def frame(self, ctx, f, w):
        fs = floor_samples(ctx, f.t)
        return None if fs is None else w["floor"] * floor_coverage(f.means, fs, ctx.spacing)


FLOOR = FloorTerm("floor", (("floor", 0.0),), needs=("floor",))
