"""The renderer's native backend: projection and rasterisation as autograd functions over the
ops of the one native extension (``gf_core.native``: ``csrc/render/``)."""

from __future__ import annotations

import torch

from ..native import available, has_cuda, load, unavailable_reason  # noqa: F401 - the backend's state, for render()


def _zeros_if_none(g, like):
    return torch.zeros_like(like) if g is None else g


class ProjectFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, scales, quats, opacities, sh, viewmat, intr, width, height, near,
                min_alpha, degree):
        ext = load()
        m2d, con, dep, col, radii = ext.project_forward(means, scales, quats, opacities, sh, viewmat,
                                                        intr, width, height, near, min_alpha, degree)
        ctx.save_for_backward(means, scales, quats, sh, viewmat, intr, radii)
        ctx.cfg = (width, height, near, degree)
        ctx.mark_non_differentiable(radii)
        return m2d, con, dep, col, radii

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, g_col, _g_radii):
        means, scales, quats, sh, viewmat, intr, radii = ctx.saved_tensors
        width, height, near, degree = ctx.cfg
        n, c = means.shape[0], sh.shape[2]
        g_m2d = _zeros_if_none(g_m2d, means[:, :2])
        g_con = _zeros_if_none(g_con, means)
        g_dep = _zeros_if_none(g_dep, means[:, 0])
        g_col = g_col if g_col is not None else means.new_zeros(n, c)
        gm, gs, gq, gsh = load().project_backward(means, scales, quats, sh, viewmat, intr, width, height,
                                                  near, degree, radii, g_m2d, g_con, g_dep, g_col)
        return gm, gs, gq, None, gsh, None, None, None, None, None, None, None


class InvalidInput(ValueError):
    """The projection found Gaussians with non-finite values, negative scales or opacities
    outside [0, 1] (flagged as radius -1); ``render`` turns this into a message naming them."""


def bin_gaussians(means2d, depths, radii, width: int, height: int, tile: int):
    """Tile/Gaussian pairs sorted by tile, then depth (stable): (offsets (tiles+1,), ids (pairs,),
    number of invalid Gaussians (1,) on the CPU)."""
    return load().bin_gaussians(means2d.detach(), depths.detach(), radii, width, height, tile)


class RasterizeFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, background, radii, depths, width, height,
                tile, min_alpha):
        ext = load()
        offsets, ids, invalid = ext.bin_gaussians(means2d.detach(), depths.detach(), radii, width, height, tile)
        if int(invalid[0]):
            raise InvalidInput(f"{int(invalid[0])} Gaussians have invalid inputs")
        out, T, nc = ext.rasterize_forward(means2d, conics, opacities, features, background, radii, offsets, ids,
                                           width, height, tile, min_alpha)
        ctx.save_for_backward(means2d, conics, opacities, radii, features, background, offsets, ids, T, nc)
        ctx.cfg = (width, height, tile, min_alpha)
        return out, T

    @staticmethod
    def backward(ctx, g_out, g_T):
        means2d, conics, opacities, radii, features, background, offsets, ids, T, nc = ctx.saved_tensors
        width, height, tile, min_alpha = ctx.cfg
        g_out = _zeros_if_none(g_out, means2d.new_zeros(height, width, features.shape[1]))
        g_T = _zeros_if_none(g_T, T)
        gm, gc, go, gf = load().rasterize_backward(means2d, conics, opacities, radii, features, background,
                                                   offsets, ids, T, nc, g_out, g_T, width, height,
                                                   tile, min_alpha)
        return gm, gc, go, gf, None, None, None, None, None, None, None
