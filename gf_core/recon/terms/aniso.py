"""Anisotropy (paper Eq. 8): L_aniso = mean_i || s_i / V_i^(1/3) - (1, 1, 1) ||^2."""

from __future__ import annotations

import torch

from .base import Term


def anisotropy(scales: torch.Tensor) -> torch.Tensor:
    """L_aniso = mean_i || s_i / V_i^(1/3) - (1, 1, 1) ||^2 (Eq. 8). V_i^(1/3) is evaluated as the
    geometric mean exp(mean(log s)), which is the same number without the cube root of a product
    that underflows for tiny particles."""
    geo = torch.exp(torch.log(scales.clamp_min(1e-30)).mean(-1, keepdim=True))
    return ((scales / geo - 1.0) ** 2).sum(-1).mean()


class AnisotropyTerm(Term):
    def frame(self, ctx, f, w):
        return w["aniso"] * anisotropy(f.params["scales"])


# lambda_a of Table 1
ANISO = AnisotropyTerm("aniso", (("aniso", 0.1),), ramp="regulariser")
