"""Opacity consistency (paper Eqs. 9-10): L_op = L_MSE(alpha), every particle's opacity near the
mean (a fluid is one material)."""

from __future__ import annotations

import torch

from .base import Term


def mse_to_mean(y: torch.Tensor) -> torch.Tensor:
    """L_MSE(y) = mean_i ||y_i - mean(y)||^2 (Eq. 10); y is (N,) or (N, ...)."""
    y = y.reshape(y.shape[0], -1)
    return ((y - y.mean(0, keepdim=True)) ** 2).sum(-1).mean()


def opacity_consistency(opacities: torch.Tensor) -> torch.Tensor:
    """L_op = L_MSE(alpha) (Eq. 9)."""
    return mse_to_mean(opacities)


class OpacityTerm(Term):
    def frame(self, ctx, f, w):
        return w["opacity"] * opacity_consistency(f.params["opacities"])


# lambda_o of Table 1
OPACITY = OpacityTerm("opacity", (("opacity", 0.01),))
