"""A simulator's continuation as the motion prior of the residual phase (not in the paper).

Inside a uniform pool the images change only at the fluid's rim: they give the particles there no
reason to move (the aperture problem of tracking), so a reconstruction of a splash stands still
where the fluid flows, and its kinetic energy after an impact is a fraction of the truth's. A
particle simulator carries that flow. At the start of the residual phase (``phases.residuals_from``)
the decoded particles at the frame ``guide.start`` (seconds into the clip) are simulated through
the clip's later training frames (``sim.solver_for_particles`` + ``sim.run_frames``, as ``gf-cli
predict`` continues a reconstruction: the rest state from the particles themselves, the scene box as
the domain, velocities from the decoded positions one frame either side, averaged over each
particle's neighbours). ``guide.start_at = "contact"`` finds the start frame itself: the last one
before the decoded fluid meets the floor or a wall. The position residuals start where the
simulation puts each particle, and ``loss.residual_motion`` measures the residuals' motion
against the simulation's instead of against none. The images then move the surface where they
show it; where they show nothing the particles keep the simulated flow.

Data flow: decoded positions (F, N, 3) at the training frames -> the start frame -> positions and
velocities there -> the simulation -> simulated positions at the later frames -> ``guide_dp`` (N, F, 3),
the position residuals that decode to them (the current ones before the start), kept in ``FluidModel.fixed``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import InputError

SOLVERS = ("none", "dfsph", "pbf")
BEFORE = ("decoder", "ballistic")
START_AT = ("seconds", "contact")
CONTACT_FRACTION = 0.05  # start_at = "contact": the share of the particles near a wall that makes a contact
FIT_CAP = 4.0            # viscosity_fit: nearest distances are capped at this many particle spacings


@dataclass
class GuideConfig:
    """``[guide]`` of the presets (every key documented in ``presets/water.toml``)."""

    solver: str = "none"      # none | dfsph | pbf
    start: float = 0.0        # the first simulated frame: the training frame at or after this many seconds
    start_at: str = "seconds"  # seconds (``start``) | contact (the frame before the fluid first meets a wall)
    viscosity: float = 0.0    # the simulated fluid's kinematic viscosity (m^2/s)
    before: str = "decoder"   # the frames before the start: decoder (as decoded) | ballistic (free flight back)
    # candidate viscosities (m^2/s): the one whose short run fits the decoded motion best is simulated
    viscosity_fit: list = field(default_factory=list)
    fit_frames: int = 6       # viscosity_fit: the frames after the start each candidate is compared over

    def validate(self, where: str) -> "GuideConfig":
        if self.solver not in SOLVERS:
            raise InputError(where, f"guide.solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.start_at not in START_AT:
            raise InputError(where, f"guide.start_at must be one of {', '.join(START_AT)}, got {self.start_at!r}")
        if self.before not in BEFORE:
            raise InputError(where, f"guide.before must be one of {', '.join(BEFORE)}, got {self.before!r}")
        return self  # with solver = "none" the guide is off, viscosity_fit and all


def start_frame(times_s, start: float) -> int:
    """The index of the first training frame (``times_s``, seconds, increasing) at or after
    ``start`` seconds into the clip."""
    t = np.asarray(times_s, np.float64)
    return int(np.searchsorted(t - t[0], start - 1e-9))


def contact_frame(decoded: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, spacing: float,
                  fraction: float = CONTACT_FRACTION) -> int | None:
    """The first frame of ``decoded`` (F, N, 3) in which at least ``fraction`` of the particles lie
    within ``spacing`` of a face of the box [lo, hi] (the particle centres' box: the floor, or a
    wall the fluid runs into); None when the fluid never meets one."""
    gap = torch.minimum(decoded - lo, hi - decoded).min(-1).values  # (F, N): distance to the nearest face
    near = (gap < spacing).to(decoded.dtype).mean(-1)
    hit = torch.nonzero(near >= fraction)
    return int(hit[0, 0]) if hit.numel() else None


def smoothed_velocities(x: torch.Tensor, v: torch.Tensor, radius: float) -> torch.Tensor:
    """Each particle's velocity averaged with its neighbours' within ``radius`` (itself included):
    velocities from decoded positions carry the residuals' shuffle, which no neighbour shares."""
    from ..sph.neighbors import neighbor_pairs

    i, j = neighbor_pairs(x, radius, include_self=True)
    total = torch.zeros_like(v).index_add_(0, i, v[j])
    count = torch.zeros(x.shape[0], dtype=v.dtype, device=v.device).index_add_(0, i, torch.ones_like(i, dtype=v.dtype))
    return total / count.clamp_min(1.0)[:, None]


def guide_start(cfg: GuideConfig, times, decoded: torch.Tensor, lo, hi, spacing: float) -> tuple[int, dict]:
    """The start frame's index and how it was chosen: ``cfg.start`` seconds into the clip, or with
    ``start_at = "contact"`` the frame before the decoded fluid first meets a face of the box (the
    last frame of free flight; 0 for fluid that rests on the floor from the start, the last frame
    for fluid that never meets one)."""
    if cfg.start_at == "seconds":
        return start_frame(times, cfg.start), {"start_at": "seconds"}
    c = contact_frame(decoded, lo, hi, spacing)
    j0 = len(times) - 1 if c is None else max(c - 1, 0)
    return j0, {"start_at": "contact", "contact_frame": c}


def chamfer_spacings(a: torch.Tensor, b: torch.Tensor, spacing: float, cap: float = FIT_CAP) -> float:
    """The symmetric Chamfer distance between point sets ``a`` and ``b`` ((N, 3), (M, 3)): the mean
    of both directions' nearest distances, in particle spacings, each capped at ``cap`` spacings."""
    from ..sph.neighbors import knn

    r = cap * spacing
    da = knn(a, 1, r, b)[1][:, 0].clamp_max(r)
    db = knn(b, 1, r, a)[1][:, 0].clamp_max(r)
    return float(0.5 * (da.mean() + db.mean()) / spacing)


def fit_viscosity(cfg: GuideConfig, continuation, decoded: torch.Tensor, spacing: float) -> tuple[float, list]:
    """The viscosity of ``cfg.viscosity_fit`` whose continuation over the ``cfg.fit_frames`` frames
    after the start stays closest to the decoded particles there (``decoded`` (K + 1, N, 3), the
    start frame first): the symmetric Chamfer distance (``chamfer_spacings``) averaged over those
    frames. ``continuation(viscosity)`` -> the simulated positions there (K + 1, N, 3). The
    images show how far the fluid spreads after it lands: a viscous fluid slumps, water runs up
    the walls. Returns the best viscosity and every candidate's score."""
    k = decoded.shape[0] - 1
    scores = []
    for nu in cfg.viscosity_fit:
        pos = continuation(nu).to(decoded.dtype)
        scores.append(float(np.mean([chamfer_spacings(pos[i], decoded[i], spacing) for i in range(1, k + 1)])))
    best = int(np.argmin(scores))
    return float(cfg.viscosity_fit[best]), [{"viscosity": nu, "chamfer": sc} for nu, sc in zip(cfg.viscosity_fit, scores)]


@torch.no_grad()
def simulate_guide(model, times_s, cfg: GuideConfig, *, spacing: float, log=print) -> tuple[torch.Tensor, dict]:
    """The position residuals (N, F, 3) that put each particle where a simulation from the start
    frame (``guide_start``) carries it at each later training frame (``times_s``, seconds: the
    residuals' knots), given the model as it is now (its decoder and its current residuals, which
    the frames before the start keep); ``spacing``: the reconstruction's particle spacing (metres).
    Returns them and a report."""
    from ..sim import Domain, prepare_particles, run_frames, solver_for_particles

    times = np.asarray(times_s, np.float64)
    dec = model.decoder
    if dec is None or dec.knots is None or dec.residual_dp.shape[1] != len(times):
        raise InputError("guide", "a simulated guide needs the decoder's position residuals at every training frame")
    out = dec.residual_dp.detach().clone()
    # decoded positions before the box holds them: residuals that reach the simulated positions from there
    decoded = torch.stack([p["unclamped"] for p in model.at_many(list(times), with_unclamped=True)])  # (F, N, 3)
    held_all = torch.maximum(torch.minimum(decoded, model._hi), model._lo)  # where the box holds them
    j0, how = guide_start(cfg, times, held_all, model._lo, model._hi, spacing)
    report = {"solver": cfg.solver, **how, "start_frame": j0, "frames": max(len(times) - 1 - j0, 0)}
    if j0 >= len(times) - 1 or len(model) < 2:
        log(f"guide: nothing to simulate (start frame {j0} is the clip's last)" if len(model) >= 2 else
            f"guide: nothing to simulate ({len(model)} particle)")
        return out, report
    held = held_all[j0]
    a, b = max(j0 - 1, 0), j0 + 1
    vel = (decoded[b] - decoded[a]) / float(times[b] - times[a])
    dt = float(np.median(np.diff(times[j0:])))
    domain = Domain(tuple(map(float, model.bounds.lo)), tuple(map(float, model.bounds.hi)))
    dev = model.means.device
    wall0 = time.perf_counter()
    gravity = None  # the solver's, for the ballistic frames before the start

    runs = {}  # viscosity -> its simulation so far: [solver, x, v, positions (list, dt apart)]

    def continuation(viscosity: float, last: int) -> torch.Tensor:
        """The decoded particles at the start frame simulated through the training frame ``last``:
        their positions at the training frames j0..last, (last - j0 + 1, N, 3). A viscosity
        simulated before goes on from where its simulation stopped (the same solver, as an
        uninterrupted run steps: the fit's candidate is not simulated twice)."""
        nonlocal gravity
        frames = int(round((times[last] - times[j0]) / dt))
        if viscosity not in runs:
            sol = solver_for_particles(held.cpu().numpy(), domain, cfg.solver, viscosity=viscosity, device=dev,
                                       where="guide")
            v0 = smoothed_velocities(held, vel, 2.0 * sol.spacing)
            x, v, _ = prepare_particles(held.cpu().numpy(), v0.cpu().numpy(), sol.domain, sol.spacing)
            runs[viscosity] = [sol, torch.as_tensor(x, dtype=torch.float32, device=dev),
                               torch.as_tensor(v, dtype=torch.float32, device=dev), []]
        sol, x, v, positions = runs[viscosity]
        done = len(positions) - 1  # frames simulated so far (-1: none, not even the start)
        if frames > done:
            res = run_frames(sol, x, v, fps=1.0 / dt, seconds=frames * dt, start_frame=max(done, 0),
                             measure_every_step=False)
            positions.extend(res.positions)
            report.update(steps=report.get("steps", 0) + len(res.steps), spacing=float(sol.spacing))
        gravity = sol.g
        k = np.clip(np.rint((times[j0:last + 1] - times[j0]) / dt).astype(np.int64), 0, frames)
        return torch.as_tensor(np.stack([positions[i] for i in k]), dtype=out.dtype, device=out.device)

    viscosity = cfg.viscosity
    if cfg.viscosity_fit:
        kf = min(cfg.fit_frames, len(times) - 1 - j0)
        viscosity, fits = fit_viscosity(cfg, lambda nu: continuation(nu, j0 + kf), held_all[j0:j0 + kf + 1], spacing)
        report["viscosity_fit"] = fits
        for nu in [nu for nu in runs if nu != viscosity]:
            del runs[nu]
        log("guide: viscosity fit over " + f"{kf} frames: " + ", ".join(
            f"{f['viscosity']:g} m^2/s -> {f['chamfer']:.3f}" for f in fits) + f" spacings; {viscosity:g} chosen")
    report["viscosity"] = viscosity
    pos = continuation(viscosity, len(times) - 1)  # (F - j0, N, 3)
    out[:, j0:] += (pos - decoded[j0:]).transpose(0, 1)
    if cfg.before == "ballistic" and j0 > 0:
        g = gravity.to(dtype=out.dtype, device=out.device)
        dt_back = torch.as_tensor(times[:j0] - times[j0], dtype=out.dtype, device=out.device)[:, None, None]
        fly = held[None] + vel[None] * dt_back + 0.5 * g * dt_back * dt_back  # (j0, N, 3)
        out[:, :j0] += (fly - decoded[:j0]).transpose(0, 1)
    if not bool(torch.isfinite(out).all()):
        raise InputError("guide", f"the {cfg.solver} continuation from {times[j0]:.3f} s is not finite")
    report.update(start_s=float(times[j0]), wall_s=round(time.perf_counter() - wall0, 2))
    why = "" if cfg.start_at == "seconds" else (
        " (no contact with the box's faces)" if how["contact_frame"] is None else
        f" (the fluid meets the box at frame {how['contact_frame']})")
    log(f"guide: {cfg.solver} from {times[j0]:.3f} s{why} through {report['frames']} frames, {len(model)} particles, "
        f"spacing {report['spacing'] * 1000:.1f} mm, viscosity {viscosity:g} m^2/s, {report['steps']} steps in "
        f"{report['wall_s']:.0f} s")
    return out, report


__all__ = ["GuideConfig", "simulate_guide", "start_frame", "guide_start", "contact_frame", "smoothed_velocities",
           "chamfer_spacings", "fit_viscosity",
           "SOLVERS", "BEFORE", "START_AT"]
