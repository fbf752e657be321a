"""Coherent velocities (not in the paper): a fluid's velocity field is smooth at the kernel's scale,
but the per-frame residuals let each particle carry its own motion, unseen by the images inside
the fluid; the particles' velocities then hold an incoherent part (particles trading places) that
inflates the kinetic energy and the motion that ``predict`` and motion blur take from them. This
penalises each particle's velocity against its neighbours' kernel-weighted mean, the quantity XSPH
(Monaghan 1989) blends towards; a coherent flow of any speed costs nothing.

The velocity at a training frame is the central difference of the decoded positions at its
neighbouring training frames (the Hermite residuals' tangent there; one-sided at the clip's ends).
The neighbours and their poly6 weights (Eq. 6) are the density term's lists at the drawn frame,
the weights held fixed (the term moves velocities, not particles towards each other). The term is
taken once per step, at the step's first decoded time (drawn at random like the others): its two
extra decodes per step rather than per time, with the per-time mean as its expectation.

With ``coherence_guided`` the term acts only where the simulated guide runs (``[guide]``, a known
container): with the guide's motion to follow after an impact, smoothing the velocities costs the
impact nothing; without it, the smoothed decoder flattens the impact's motion."""

from __future__ import annotations

import torch

from ...sph.kernels import poly6_sq
from .base import Term


def velocity_incoherence(v: torch.Tensor, idx: torch.Tensor, means: torch.Tensor, h: float) -> torch.Tensor:
    """mean_i |v_i - vbar_i|^2 with vbar_i = (W(0) v_i + sum_k W_ik v_k) / (W(0) + sum_k W_ik), the
    poly6 weights W_ik = W(|p_i - p_k|, h) over (N, K) neighbour indices ``idx`` (-1 = none), taken
    from ``means`` without gradient. ``v`` (N, 3) in whatever unit the caller scales it to."""
    ok = idx >= 0
    j = idx.clamp_min(0)
    with torch.no_grad():
        d = means[:, None, :] - means[j]
        w = torch.where(ok, poly6_sq((d * d).sum(-1), h), torch.zeros((), dtype=means.dtype, device=means.device))
        w0 = poly6_sq(torch.zeros((), dtype=means.dtype, device=means.device), h)
        norm = w0 + w.sum(1, keepdim=True)
        rows = torch.arange(len(idx), device=idx.device)[:, None].expand_as(idx)
        # the neighbours' weighted sum as a sparse product: its gradient is the transposed product,
        # the same sums in the same order in every run (a gather's gradient accumulates across threads)
        W = torch.sparse_coo_tensor(torch.stack([rows[ok], idx[ok]]), (w / norm)[ok].to(v.dtype),
                                    (len(idx), len(v)), check_invariants=False).coalesce()
    vbar = (w0 / norm).to(v.dtype) * v + torch.sparse.mm(W, v)
    dv = v - vbar
    return (dv * dv).sum(-1).mean()


class CoherenceTerm(Term):
    def frame(self, ctx, f, w):
        times = ctx.views.unique_times
        if len(times) < 2:
            return None
        j = ctx.frame_index(f.t)
        a, b = max(j - 1, 0), min(j + 1, len(times) - 1)
        taus = [ctx.time_map.tau(float(times[k])) for k in (a, b)]
        dp = ctx.model.decoder.forward_many(taus)["dp"]  # the canonical positions cancel in the difference
        frame = 1.0 / (len(times) - 1)                   # the mean knot step in tau
        v = (dp[1] - dp[0]) * (frame / ((taus[1] - taus[0]) * ctx.spacing))  # particle spacings per frame
        return w["coherence"] * velocity_incoherence(v, f.neighbours(), f.means, ctx.h)

    def step(self, ctx, s, w):
        return self.frame(ctx, s.frames[0], w)


COHERENCE = CoherenceTerm("coherence", (("coherence", 0.0),), phase_key=("coherence_from", 3),
                          every_key=("coherence_every", 1), guided_key=("coherence_guided", False), per="step",
                          needs=("decoder", "residuals"))
