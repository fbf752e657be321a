"""SPH number density over neighbour lists (paper Eqs. 5-6): D_i = sum_j W(|p_i - p_j|, h) with
unit mass and the poly6 kernel, self term included. Used by the density loss, the volume the
trained particles fill and the density spread of ``gf-cli evaluate``."""

from __future__ import annotations

import math

import numpy as np
import torch

from .kernels import poly6_sq
from .neighbors import knn


def sph_density(positions: torch.Tensor, nbr_i: torch.Tensor, nbr_j: torch.Tensor, h: float) -> torch.Tensor:
    """D_i = sum_j W(|p_i - p_j|, h) with unit mass (Eq. 5), self term included, over stored
    neighbour pairs (i, j), i != j. Gradients flow through the pair distances; a pair that has
    moved beyond h since the list was built contributes 0 (the kernel's support)."""
    d = positions[nbr_i] - positions[nbr_j]
    w = poly6_sq((d * d).sum(-1), h)
    w0 = 315.0 / (64.0 * math.pi * h ** 3)  # W(0) = 315 h^6 / (64 pi h^9)
    dens = torch.full((positions.shape[0],), w0, dtype=positions.dtype, device=positions.device)
    return dens.index_add(0, nbr_i, w)


class DensityFn(torch.autograd.Function):
    """D_i = W(0) + sum_k W(|x_i - x_idx[i,k]|, h), poly6, unit mass (paper Eqs. 5-6), over
    (N, K) neighbour indices (-1 = none): the native op (``native/csrc/sph/``) with its
    hand-written backward through the pair distances."""

    @staticmethod
    def forward(ctx, x, idx, h):
        from .. import native

        ctx.save_for_backward(x, idx)
        ctx.h = float(h)
        return native.load().sph_density_forward(x, idx, float(h))[0]

    @staticmethod
    def backward(ctx, g):
        from .. import native

        x, idx = ctx.saved_tensors
        return native.load().sph_density_backward(x, idx, ctx.h, g.contiguous())[0], None, None


def sph_density_knn(positions: torch.Tensor, idx: torch.Tensor, h: float) -> torch.Tensor:
    """``sph_density`` over (N, K) neighbour indices (-1 = none, as ``neighbors.knn`` returns):
    one native call (C++ or CUDA, hand-written backward) where the extension is built, else the
    pair form above."""
    from .. import native

    dev = positions.device.type
    if native.available() and (dev == "cpu" or (dev == "cuda" and native.has_cuda())):
        return DensityFn.apply(positions.contiguous(), idx.contiguous(), h)
    rows = torch.arange(positions.shape[0], device=positions.device)[:, None].expand_as(idx)
    ok = idx >= 0
    return sph_density(positions, rows[ok], idx[ok], h)


def particle_volume(frames, h: float, k: int = 256) -> float:
    """The fluid volume the particles fill, each standing for an equal share: N / the median SPH
    number density sum_j W(|p_i - p_j|, h) (the poly6 kernel of Eq. 6, self term included, at most
    ``k`` neighbours within h), the mean over ``frames`` ((N, 3) positions each). The kernel
    integrates to 1, so inside a fluid of n particles per cubic metre the sum is n; the median
    sits between the full interior and the thinned surface. The visual hull of a few views holds
    far more than the fluid, so a mass from its volume inflates every energy."""
    vols = []
    for x in frames:
        x = torch.as_tensor(x).detach().float()
        if x.shape[0] == 0:
            continue
        idx, _ = knn(x, k, h, sorted=False)
        vols.append(x.shape[0] / float(sph_density_knn(x, idx, h).median()))
    if not vols:
        raise ValueError("particle_volume: no particles in any frame")
    return float(np.mean(vols))


__all__ = ["sph_density", "sph_density_knn", "DensityFn", "particle_volume"]
