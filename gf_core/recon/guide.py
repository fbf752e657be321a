"""A simulator's continuation as the motion prior of the residual phase (not in the paper).

Inside a uniform pool the images change only at the fluid's rim: they give the particles there no
reason to move (the aperture problem of tracking), so a reconstruction of a splash stands still
where the fluid flows, and its kinetic energy after an impact is a fraction of the truth's. A
particle simulator carries that flow. At the start of the residual phase (``phases.residuals_from``)
the decoded particles at the frame ``guide.start`` (seconds into the clip) are simulated through
the clip's later training frames (``sim.solver_for_particles`` + ``sim.run_frames``, as ``gf-cli
predict`` continues a reconstruction: the rest state from the particles themselves, the scene box as
the domain, velocities from the decoded positions one frame either side); the position residuals
start where that puts each particle, and ``loss.residual_motion`` measures the residuals' motion
against the simulation's instead of against none. The images then move the surface where they
show it; where they show nothing the particles keep the simulated flow.

Data flow: decoded positions (F, N, 3) at the training frames -> positions and velocities at the
start frame -> the simulation -> simulated positions at the later frames -> ``guide_dp`` (N, F, 3),
the position residuals that decode to them (the current ones before the start), kept in ``FluidModel.fixed``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError

SOLVERS = ("none", "dfsph", "pbf")
BEFORE = ("decoder", "ballistic")


@dataclass
class GuideConfig:
    """``[guide]`` of the presets (every key documented in ``presets/water.toml``)."""

    solver: str = "none"      # none | dfsph | pbf
    start: float = 0.0        # the first simulated frame: the training frame at or after this many seconds
    viscosity: float = 0.0    # the simulated fluid's kinematic viscosity (m^2/s)
    before: str = "decoder"   # the frames before the start: decoder (as decoded) | ballistic (free flight back)

    def validate(self, where: str) -> "GuideConfig":
        if self.solver not in SOLVERS:
            raise InputError(where, f"guide.solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.before not in BEFORE:
            raise InputError(where, f"guide.before must be one of {', '.join(BEFORE)}, got {self.before!r}")
        return self


def start_frame(times_s, start: float) -> int:
    """The index of the first training frame (``times_s``, seconds, increasing) at or after
    ``start`` seconds into the clip."""
    t = np.asarray(times_s, np.float64)
    return int(np.searchsorted(t - t[0], start - 1e-9))


@torch.no_grad()
def simulate_guide(model, times_s, cfg: GuideConfig, *, log=print) -> tuple[torch.Tensor, dict]:
    """The position residuals (N, F, 3) that put each particle where a simulation from the frame
    ``cfg.start`` (seconds into the clip) carries it at each later training frame (``times_s``,
    seconds: the residuals' knots), given the model as it is now (its decoder and its current
    residuals, which the frames before the start keep). Returns them and a report."""
    from ..sim import Domain, prepare_particles, run_frames, solver_for_particles

    times = np.asarray(times_s, np.float64)
    dec = model.decoder
    if dec is None or dec.knots is None or dec.residual_dp.shape[1] != len(times):
        raise InputError("guide", "a simulated guide needs the decoder's position residuals at every training frame")
    j0 = start_frame(times, cfg.start)
    out = dec.residual_dp.detach().clone()
    report = {"solver": cfg.solver, "start_frame": j0, "frames": max(len(times) - 1 - j0, 0)}
    if j0 >= len(times) - 1:
        return out, report
    # decoded positions before the box holds them: residuals that reach the simulated positions from there
    decoded = torch.stack([p["unclamped"] for p in model.at_many(list(times), with_unclamped=True)])  # (F, N, 3)
    held = torch.maximum(torch.minimum(decoded[j0], model._hi), model._lo)  # where the box holds them
    a, b = max(j0 - 1, 0), j0 + 1
    vel = (decoded[b] - decoded[a]) / float(times[b] - times[a])
    dt = float(np.median(np.diff(times[j0:])))
    domain = Domain(tuple(map(float, model.bounds.lo)), tuple(map(float, model.bounds.hi)))
    dev = model.means.device
    wall0 = time.perf_counter()
    sol = solver_for_particles(held.cpu().numpy(), domain, cfg.solver, viscosity=cfg.viscosity, device=dev,
                               where="guide")
    x, v, _ = prepare_particles(held.cpu().numpy(), vel.cpu().numpy(), sol.domain, sol.spacing)
    frames = int(round((times[-1] - times[j0]) / dt))
    res = run_frames(sol, torch.as_tensor(x, dtype=torch.float32, device=dev),
                     torch.as_tensor(v, dtype=torch.float32, device=dev), fps=1.0 / dt, seconds=frames * dt)
    positions = np.stack(res.positions)  # (frames + 1, N, 3)
    k = np.clip(np.rint((times[j0:] - times[j0]) / dt).astype(np.int64), 0, len(positions) - 1)
    pos = torch.as_tensor(positions[k], dtype=out.dtype, device=out.device)  # (F - j0, N, 3)
    out[:, j0:] += (pos - decoded[j0:]).transpose(0, 1)
    if cfg.before == "ballistic" and j0 > 0:
        g = sol.g.to(dtype=out.dtype, device=out.device)
        dt_back = torch.as_tensor(times[:j0] - times[j0], dtype=out.dtype, device=out.device)[:, None, None]
        fly = held[None] + vel[None] * dt_back + 0.5 * g * dt_back * dt_back  # (j0, N, 3)
        out[:, :j0] += (fly - decoded[:j0]).transpose(0, 1)
    if not bool(torch.isfinite(out).all()):
        raise InputError("guide", f"the {cfg.solver} continuation from {times[j0]:.3f} s is not finite")
    report.update(start_s=float(times[j0]), steps=len(res.steps), spacing=float(sol.spacing),
                  wall_s=round(time.perf_counter() - wall0, 2))
    log(f"guide: {cfg.solver} from {times[j0]:.3f} s through {report['frames']} frames, {len(model)} particles, "
        f"spacing {sol.spacing * 1000:.1f} mm, {report['steps']} steps in {report['wall_s']:.0f} s")
    return out, report


__all__ = ["GuideConfig", "simulate_guide", "start_frame", "SOLVERS", "BEFORE"]
