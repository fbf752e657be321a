"""SPH smoothing kernels on pair arrays (support radius h; W = 0 beyond h).

cubic spline (PBF's XSPH and its density measurement): Monaghan 1992 in the normalisation of
SPlisHSPlasH.
Wendland C2 (DFSPH): Wendland 1995, in 3D W(q) = 21 / (2 pi h^3) (1 - q)^4 (1 + 4 q), q = r / h.
Dehnen & Aly 2012 show it has no pairing instability; here the simple-cubic lattice of a fluid
under hydrostatic pressure is stable with it and unstable with the cubic spline (BENCHMARKS.md).
poly6 (PBF densities; paper Eq. 6) and spiky gradient (PBF constraint gradients): Mueller 2003.
Gradients of coincident pairs (r = 0) are zero, never NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

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
    return poly6_sq(r * r, h)


def poly6_sq(r2: torch.Tensor, h: float) -> torch.Tensor:
    """``poly6`` of the squared distance (no square root where pairs come as squared distances)."""
    return 315.0 / (64.0 * math.pi * h ** 9) * (h * h - r2).clamp_min(0.0) ** 3


def spiky_grad(d: torch.Tensor, r: torch.Tensor, h: float) -> torch.Tensor:
    f = -45.0 / (math.pi * h ** 6) * (h - r).clamp_min(0.0) ** 2
    scale = torch.where(r > 1e-9 * h, f / r.clamp_min(1e-30), torch.zeros_like(r))
    return d * scale[:, None]


def wendland(r: torch.Tensor, h: float) -> torch.Tensor:
    q = (r / h).clamp(max=1.0)
    return 21.0 / (2.0 * math.pi * h ** 3) * (1.0 - q) ** 4 * (1.0 + 4.0 * q)


def wendland_grad(d: torch.Tensor, r: torch.Tensor, h: float) -> torch.Tensor:
    """grad_i W(x_i - x_j); dW/dr = 21 / (2 pi h^4) d/dq[(1 - q)^4 (1 + 4q)] = -210 / (pi h^4) q (1 - q)^3."""
    q = (r / h).clamp(max=1.0)
    f = -210.0 / (math.pi * h ** 4) * q * (1.0 - q) ** 3
    scale = torch.where(r > 1e-9 * h, f / r.clamp_min(1e-30), torch.zeros_like(r))
    return d * scale[:, None]


def wendland_zero(h: float) -> float:
    return 21.0 / (2.0 * math.pi * h ** 3)


@dataclass(frozen=True)
class Kernel:
    """A kernel with its gradient and its value at r = 0, passed to the shared solver pieces."""

    name: str
    W: Callable
    grad: Callable
    zero: Callable


CUBIC = Kernel("cubic", cubic, cubic_grad, cubic_zero)
WENDLAND = Kernel("wendland", wendland, wendland_grad, wendland_zero)
