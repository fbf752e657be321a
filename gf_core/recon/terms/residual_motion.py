"""Residuals that keep each particle's identity (not in the paper): the position residuals R are
fitted frame by frame, and the images cannot tell which particle is which inside the fluid, so
without this term the particles may trade places from one frame to the next while every frame's
image stays right; their velocities (and the kinetic energy, motion blur, predictions that use
them) then measure that shuffle, not the flow. With a frozen decoder carrying the bulk motion,
this penalises only the motion the residuals add. With a simulated guide (``[guide]``,
``recon/guide.py``) the residuals are measured from the guide's (``FluidModel.fixed["guide_dp"]``):
the motion they add to the simulation's."""

from __future__ import annotations

import torch

from .base import Term


def residual_change(r: torch.Tensor, r_nbrs: torch.Tensor, spacing: float) -> torch.Tensor:
    """mean_i of |R_i(k) - R_i(k')|^2 / spacing^2 over the neighbouring training frames k' of
    frame k (the mean over them), in particle spacings per frame. ``r`` (N, 3): the residual at
    frame k; ``r_nbrs`` (N, M, 3) at its M neighbours."""
    d = r_nbrs - r[:, None, :]
    return (d * d).sum(-1).mean() / (spacing * spacing)


class ResidualMotionTerm(Term):
    def frame(self, ctx, f, w):
        """The drawn frame's position residual against the neighbouring training frames' (one at
        the clip's ends). The knots are the training frames, so the residual there is the
        parameter itself (no interpolation)."""
        j = ctx.frame_index(f.t)
        r = ctx.model.decoder.residual_dp
        nbrs = [k for k in (j - 1, j + 1) if 0 <= k < r.shape[1]]
        here, there = r[:, j], r[:, nbrs]
        g = ctx.model.fixed.get("guide_dp")
        if g is not None:
            here, there = here - g[:, j], there - g[:, nbrs]
        return w["residual_motion"] * residual_change(here, there, ctx.spacing)


RESIDUAL_MOTION = ResidualMotionTerm("residual_motion", (("residual_motion", 0.0),), phases="residuals",
                                     needs=("decoder", "residuals"))
