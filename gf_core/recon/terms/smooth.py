"""Smooth motion (not in the paper): the per-frame residuals may let particles jump about between
frames unseen by the images; this penalises each particle's acceleration at the drawn frame, from
its decoded positions there and at the neighbouring training frames, through the residuals (with a
frozen decoder the MLP's part comes from its cache, so only the residuals get gradients)."""

from __future__ import annotations

import torch

from .base import Term


def acceleration(dp_prev: torch.Tensor, dp: torch.Tensor, dp_next: torch.Tensor, h0: float, h1: float,
                 frame: float, spacing: float) -> torch.Tensor:
    """mean_i |a_i|^2 of each particle's acceleration at a training frame, from its positions at
    that frame and its two neighbours (the non-uniform second difference, taus h0 before and h1
    after), in particle spacings per frame^2 (``frame``: the mean knot step in tau):

        a_i = 2 [h0 (p_i(+) - p_i) - h1 (p_i - p_i(-))] / (h0 h1 (h0 + h1)) * frame^2 / spacing

    ``dp_*`` (N, 3): positions, or anything that differs from them by the same offset at the
    three times (the canonical positions cancel)."""
    a = 2.0 * (h0 * (dp_next - dp) - h1 * (dp - dp_prev)) / (h0 * h1 * (h0 + h1)) * (frame ** 2 / spacing)
    return (a * a).sum(-1).mean()


class SmoothTerm(Term):
    def frame(self, ctx, f, w):
        times = ctx.views.unique_times
        j = ctx.frame_index(f.t)
        if j == 0 or j == len(times) - 1:  # the clip's first and last frame have one neighbour
            return None
        taus = [ctx.time_map.tau(float(times[k])) for k in (j - 1, j, j + 1)]
        dp = ctx.model.decoder.forward_many(taus)["dp"]
        frame = 1.0 / (len(times) - 1)
        return w["smooth"] * acceleration(dp[0], dp[1], dp[2], taus[1] - taus[0], taus[2] - taus[1], frame,
                                          ctx.spacing)


SMOOTH = SmoothTerm("smooth", (("smooth", 0.0),), phases="residuals", needs=("decoder", "residuals"))
