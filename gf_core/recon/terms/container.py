"""The container (not in the paper): how far the decoded positions lie beyond the scene box before
the box holds them (``FluidModel._bounded``), in particle spacings, mean over all particles. The
clamp draws a particle that the decoder carried through a wall at that wall, where its gradient
along that axis is 0: nothing stops the decoder carrying it further, and once it lies well beyond,
neither the images nor any other term can move it along that axis again (a splash's fluid decoded
through the floor stays flattened on it). This term pulls the decoded position back to the wall
it crossed, through whatever decoded it (canonical particle, theta, Phi, residuals); inside the box
it is 0, and so is its gradient."""

from __future__ import annotations

import torch

from .base import Term


def beyond_box(positions: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, spacing: float) -> torch.Tensor:
    """Mean over the particles of the distance (L1 over the axes, in particle spacings) from each
    of ``positions`` (N, 3) to the box [lo, hi]; 0 for a particle inside."""
    out = torch.relu(lo - positions) + torch.relu(positions - hi)
    return out.sum(-1).mean() / spacing


class ContainerTerm(Term):
    def frame(self, ctx, f, w):
        raw = f.params.get("unclamped")
        if raw is None:  # a frame decoded without the decoder: the canonical particles stay inside
            return None
        return w["container"] * beyond_box(raw, ctx.model._lo, ctx.model._hi, ctx.spacing)


CONTAINER = ContainerTerm("container", (("container", 0.0),), phases="dynamic", needs=("decoder",))
