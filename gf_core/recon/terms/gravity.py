"""Gravity (not in the paper): the potential energy of every particle, its height above the floor in
particle spacings (mean over all particles), through each frame's position residual only. The images
place the opaque particles; the rest of a liquid sits where the views cannot see into it, and of all
the ways to fill the views' hull with one volume of fluid (``incompressible``) a liquid takes the
lowest. Needs the floor (gravity along -z); no pull reaches the canonical particles or the decoder."""

from __future__ import annotations

import torch

from .base import Term
from .settle import settling, through_residual


class GravityTerm(Term):
    def frame(self, ctx, f, w):
        pos = through_residual(ctx, f)
        everyone = torch.ones(pos.shape[0], dtype=torch.bool, device=pos.device)
        return w["gravity"] * settling(pos, everyone, float(ctx.model.bounds.lo[2]), ctx.spacing)


GRAVITY = GravityTerm("gravity", (("gravity", 0.0),), phases="residuals", needs=("decoder", "residuals", "floor"))
