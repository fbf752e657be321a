"""SPH smoothing kernels on pair arrays (support radius h; W = 0 beyond h).

cubic spline (DFSPH, measurements): Monaghan 1992 in the normalisation of SPlisHSPlasH.
poly6 (PBF densities; paper Eq. 6) and spiky gradient (PBF constraint gradients): Mueller 2003.
Gradients of coincident pairs (r = 0) are zero, never NaN.
"""

from __future__ import annotations

import math

import torch


def cubic(r: torch.Tensor, h: float) -> torch.Tensor:
    q = r / h
    k = 8.0 / (math.pi * h ** 3)
    inner = k * (6.0 * q ** 3 - 6.0 * q ** 2 + 1.0)
    outer = k * 2.0 * (1.0 - q).clamp_min(0.0) ** 3
    return torch.where(q <= 0.5, inner, outer)


def cubic_grad(d: torch.Tensor, r: torch.Tensor, h: float) -> torch.Tensor:
    """grad_i W(x_i - x_j) for pair offsets d = x_i - x_j (P, 3) with lengths r (P,)."""
    q = r / h
    l = 48.0 / (math.pi * h ** 3)
    f = torch.where(q <= 0.5, l * q * (3.0 * q - 2.0), -l * (1.0 - q).clamp_min(0.0) ** 2)
    scale = torch.where(r > 1e-9 * h, f / (h * r.clamp_min(1e-30)), torch.zeros_like(r))
    return d * scale[:, None]


def cubic_zero(h: float) -> float:
    return 8.0 / (math.pi * h ** 3)


def poly6(r: torch.Tensor, h: float) -> torch.Tensor:
    """Paper Eq. (6): 315 / (64 pi h^9) (h^2 - r^2)^3 for r <= h."""
    return 315.0 / (64.0 * math.pi * h ** 9) * (h * h - r * r).clamp_min(0.0) ** 3


def spiky_grad(d: torch.Tensor, r: torch.Tensor, h: float) -> torch.Tensor:
    f = -45.0 / (math.pi * h ** 6) * (h - r).clamp_min(0.0) ** 2
    scale = torch.where(r > 1e-9 * h, f / r.clamp_min(1e-30), torch.zeros_like(r))
    return d * scale[:, None]
