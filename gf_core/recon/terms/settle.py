"""Settling (not in the paper): in frames whose floor the views see wet (``floor.floor_points``),
the particles that hang over it with no particle below (a 45-degree cone within h) are pulled
down: fluid cannot hover over a pool, but views looking down at a sheet cannot tell it from fluid
held higher along their rays. Through each frame's position residual only, so that no pull
reaches the canonical particles, the decoder, or the frames where the fluid falls free."""

from __future__ import annotations

import torch

from .base import Term
from .floor import floor_points


@torch.no_grad()
def unsupported(positions: torch.Tensor, idx: torch.Tensor, spacing: float, floor: float) -> torch.Tensor:
    """(N,) bool: particles (N, 3) with no neighbour (``idx`` (N, K), -1 = none, as
    ``neighbors.knn`` returns) below them within a 45-degree cone at least half a spacing lower,
    and more than one spacing above ``floor`` (gravity along -z): fluid held up by nothing."""
    z = positions[:, 2]
    ok = idx >= 0
    q = positions[idx.clamp_min(0)]  # (N, K, 3)
    dz = z[:, None] - q[..., 2]
    dh = (positions[:, None, :2] - q[..., :2]).norm(dim=-1)
    below = ok & (dz > 0.5 * spacing) & (dh < dz)
    return ~below.any(1) & (z > floor + spacing)


def through_residual(ctx, f) -> torch.Tensor:
    """The frame's decoded positions (N, 3) with a gradient that reaches its position residual only
    (the residual's value is already in them): a pull on these moves no canonical particle, no
    decoder weight and no other frame."""
    tau = torch.full((1,), ctx.time_map.tau(f.t), dtype=f.means.dtype, device=ctx.device)
    r = ctx.model.decoder.residual_at(tau, "dp")[0][0]
    return f.means.detach() + (r - r.detach())


def settling(positions: torch.Tensor, gate: torch.Tensor, floor: float, spacing: float) -> torch.Tensor:
    """Potential energy of the ``gate``d particles (N,) bool, their height above ``floor`` in
    particle spacings summed over them and divided by all N (gravity along -z)."""
    height = (positions[:, 2] - floor) / spacing
    return torch.where(gate, height, torch.zeros_like(height)).mean()


class SettleTerm(Term):
    def frame(self, ctx, f, w):
        """``settling`` gated to the particles that hang unsupported over the wet part of the
        floor (a floor grid cell that holds one of the floor points), through the frame's
        position residual only. A frame whose fluid does not reach the floor gets nothing."""
        nbr = f.neighbours()
        ent = floor_points(ctx, f.t)
        means = f.means
        if ent is None:
            return w["settle"] * (means.sum() * 0.0)
        wet = ent[2]
        pos = through_residual(ctx, f)
        lo = ctx.model.bounds.lo
        with torch.no_grad():
            q = torch.floor((means[:, :2].detach() - torch.as_tensor(lo[:2], dtype=means.dtype, device=ctx.device))
                            / ctx.spacing).long()
            inside = (q[:, 0] >= 0) & (q[:, 0] < wet.shape[0]) & (q[:, 1] >= 0) & (q[:, 1] < wet.shape[1])
            over = wet[q[:, 0].clamp(0, wet.shape[0] - 1), q[:, 1].clamp(0, wet.shape[1] - 1)] & inside
            # which particles hang unsupported: computed when the frame's neighbour lists are
            # (re)built (density.refresh_every) and reused with them, as slowly as they change
            held = ctx.scratch.get(("held_up", f.t))
            if held is None or held[0] is not nbr:
                held = (nbr, unsupported(means.detach(), nbr, ctx.spacing, float(lo[2])))
                ctx.scratch[("held_up", f.t)] = held
            gate = over & held[1]
        return w["settle"] * settling(pos, gate, float(lo[2]), ctx.spacing)


SETTLE = SettleTerm("settle", (("settle", 0.0),), phases="residuals", needs=("decoder", "residuals", "floor"))
