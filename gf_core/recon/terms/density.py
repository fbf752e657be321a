"""Density uniformity (paper Eq. 5): L_dens = mean_i (D_i / mean(D) - 1)^2 over the SPH number
density D (``sph.density``, poly6 of Eq. 6) of a frame's decoded particles. Neighbour lists (up
to ``density.k`` nearest within h) are kept per frame and rebuilt after ``density.refresh_every``
uses or whenever the particle set changes (``Context.neighbours``); gradients flow through the
distances of the stored pairs."""

from __future__ import annotations

import torch

from ...sph.density import sph_density_knn
from .base import Term


def density_uniformity(density: torch.Tensor) -> torch.Tensor:
    """L_dens = mean_i (D_i / mean(D) - 1)^2 (Eq. 5)."""
    return ((density / density.mean().clamp_min(1e-30) - 1.0) ** 2).mean()


class DensityTerm(Term):
    def frame(self, ctx, f, w):
        return w["density"] * density_uniformity(sph_density_knn(f.means, f.neighbours(), ctx.h))


# lambda_d of Table 1; ramps as Eq. 11's schedule says (schedule.loss_weights)
DENSITY = DensityTerm("density", (("density", 0.1),), ramp="density")
