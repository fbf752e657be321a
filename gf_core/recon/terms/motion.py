"""Least motion (not in the paper): rendering cannot tell which particle is which inside the fluid,
so particles may circulate without changing an image; this prefers the quietest motion that
explains the images."""

from __future__ import annotations

import torch

from .base import Term


def least_motion(positions: list, taus: list, spacing: float) -> torch.Tensor:
    """Sum over consecutive decoded times of mean_i |p_i(b) - p_i(a)|^2 / (spacing^2 |tau_b - tau_a|),
    a discrete integral of the squared speed (kinetic action) in particle spacings per normalised
    time. ``positions`` (T, N, 3) in the order of ``taus``."""
    order = sorted(range(len(taus)), key=lambda k: taus[k])
    total = positions[0].new_zeros(())
    for a, b in zip(order, order[1:]):
        dt = abs(taus[b] - taus[a])
        if dt > 1e-9:
            total = total + ((positions[b] - positions[a]) ** 2).sum(-1).mean() / (spacing ** 2 * dt)
    return total


class MotionTerm(Term):
    def step(self, ctx, s, w):
        if len(s.frames) < 2:
            return None
        return w["motion"] * least_motion([f.means for f in s.frames], [ctx.time_map.tau(f.t) for f in s.frames],
                                          ctx.spacing)


MOTION = MotionTerm("motion", (("motion", 0.0),), per="step", phases="dynamic", needs=("decoder",))
