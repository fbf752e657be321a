"""Volume consistency (paper Eq. 7): L_vol = mean_i (V_i / mean(V) - 1)^2, V_i = s_x s_y s_z."""

from __future__ import annotations

import torch

from .base import Term


def volume_consistency(scales: torch.Tensor) -> torch.Tensor:
    """L_vol = mean_i (V_i / mean(V) - 1)^2 with V_i = s_x s_y s_z (Eq. 7)."""
    v = scales.prod(-1)
    return ((v / v.mean().clamp_min(1e-30) - 1.0) ** 2).mean()


class VolumeTerm(Term):
    def frame(self, ctx, f, w):
        return w["volume"] * volume_consistency(f.params["scales"])


# lambda_v of Table 1
VOLUME = VolumeTerm("volume", (("volume", 0.1),), ramp="regulariser")
