"""Colour consistency (paper Eqs. 9-10): L_light = L_MSE(c) over the particles' SH coefficients."""

from __future__ import annotations

import torch

from .base import Term
from .opacity import mse_to_mean


def color_consistency(sh: torch.Tensor) -> torch.Tensor:
    """L_light = L_MSE(c) over the SH coefficients (Eq. 9)."""
    return mse_to_mean(sh)


class ColorTerm(Term):
    def frame(self, ctx, f, w):
        return w["color"] * color_consistency(f.params["sh"])


# lambda_l of Table 1
COLOR = ColorTerm("color", (("color", 1.0),))
