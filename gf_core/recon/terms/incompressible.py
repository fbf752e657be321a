"""One fluid volume at every time (not in the paper): Eq. 5's density term compares each particle
with its own frame's mean density, so a frame may inflate or compress as a whole; a liquid keeps
its volume. This penalises the spread, across the step's decoded times, of the log of each frame's
mean SPH number density (poly6 of Eq. 6, the density term's neighbour lists): with a fixed number
of particles, the same mean density means the same volume. The frames pull towards one another, so
no frame is the reference (a free-falling drop that fills the views' hull and a splash pressed
flat on the floor meet in between)."""

from __future__ import annotations

import torch

from ...sph.density import sph_density_knn
from .base import Term


def density_spread(densities: list) -> torch.Tensor:
    """Variance over frames of log mean_i D_i, for each frame's (N,) SPH number densities."""
    logs = torch.stack([d.mean().clamp_min(1e-30).log() for d in densities])
    return ((logs - logs.mean()) ** 2).mean()


class IncompressibleTerm(Term):
    def step(self, ctx, s, w):
        if len(s.frames) < 2:
            return None
        dens = [sph_density_knn(f.means, f.neighbours(), ctx.h) for f in s.frames]
        return w["incompressible"] * density_spread(dens)


INCOMPRESSIBLE = IncompressibleTerm("incompressible", (("incompressible", 0.0),), per="step", phases="dynamic",
                                    needs=("decoder",))
