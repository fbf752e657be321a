"""Continuing a reconstruction with a particle simulator: fluid prediction (paper Sec. 4.3.4,
Table 8), and the simulation after an edit (Sec. 4.3.5, Fig. 10; the edits are ``edit.py``).

Data flow, one way::

    recon.h5 --state_at(t)--> State --edit.*--> State --continue_state--> sim.h5 (+ source_index)

``State`` holds the particles at one time: positions, velocities (finite differences of the decoded
positions over a frame interval, ``state_at``) and, per particle, the index of the reconstructed
particle whose appearance it keeps (``source_index``): the continuation is rendered with the
learned Gaussians (``evaluate`` of a ``sim.h5`` that names its reconstruction).

The simulator's rest state comes from the particles themselves (``sim.common.estimate_rest_state``:
rest volume = 1 / the interior's number density, spacing = the lattice spacing of that volume), so a reconstruction packed more loosely or tightly than a
lattice is at rest as given, not compressed or expanded by the first step. The domain is the box
the reconstruction kept its particles in (recon config ``bounds``: the dataset's scene box).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..formats.hdf5 import ReconData, SimData, SimWriter, read_recon
from ..recon.model import FluidModel


@dataclass
class State:
    """Particles at one time: (N, 3) positions (m) and velocities (m/s), (N,) source indices."""

    positions: np.ndarray
    velocities: np.ndarray
    source_index: np.ndarray
    time: float
    domain: tuple                    # (lo, hi), metres
    edits: list = field(default_factory=list)
    # (solver, spacing, rest volume) fixed before editing, so that removing half the particles
    # removes half the mass instead of giving the rest twice the volume each
    rest: tuple | None = None

    def __post_init__(self):
        self.positions = np.asarray(self.positions, np.float64).reshape(-1, 3)
        self.velocities = np.asarray(self.velocities, np.float64).reshape(-1, 3)
        self.source_index = np.asarray(self.source_index, np.int64).reshape(-1)
        n = self.positions.shape[0]
        if self.velocities.shape != (n, 3) or self.source_index.shape != (n,):
            raise InputError("state", f"positions {self.positions.shape}, velocities {self.velocities.shape} and "
                                      f"source_index {self.source_index.shape} do not match")

    def __len__(self) -> int:
        return self.positions.shape[0]

    def take(self, keep: np.ndarray, edit: dict) -> "State":
        return replace(self, positions=self.positions[keep], velocities=self.velocities[keep],
                       source_index=self.source_index[keep], edits=self.edits + [edit])


def domain_of(r: ReconData, where) -> tuple:
    b = r.config.get("bounds")
    if not b:
        raise InputError(where, "the reconstruction records no scene box (config 'bounds'); a continuation "
                                "needs the box the fluid lives in")
    lo, hi = np.asarray(b["lo"], np.float64), np.asarray(b["hi"], np.float64)
    return lo, hi


def state_at(recon: ReconData | Path, t: float | None = None, *, velocity: str = "frames",
             where: str = "predict") -> State:
    """The reconstructed particles and their velocities at ``t`` seconds (default: the last
    training frame, the start of a prediction).

    ``velocity="frames"`` (default): a finite difference of the decoded positions over one training
    frame interval (central inside the clip, one-sided at its ends). The images constrain the
    decoder only at the frame times; between them the frequency encoding lets the trajectories
    wiggle, and the instantaneous derivative (``"analytic"``, dp/dt through the MLP) picks up those
    wiggles, several times the true speed (BENCHMARKS.md, "Downstream tasks")."""
    r = read_recon(recon) if not isinstance(recon, ReconData) else recon
    model = FluidModel.from_recon(r)
    times = r.config.get("frame_times_s") or [r.time_min, r.time_max]
    t = float(times[-1] if t is None else t)
    if not np.isfinite(t):
        raise InputError("--at", f"must be a finite time in seconds, got {t}")
    lo, hi = model.time_map.t_min, model.time_map.t_max
    if model.is_dynamic and not (lo - 1e-9 <= t <= hi + 1e-9):
        raise InputError("--at", f"{t:g} s is outside the reconstructed clip [{lo:g}, {hi:g}] s")
    if velocity not in ("frames", "analytic"):
        raise InputError("--velocity", f"unknown velocity source {velocity!r}; use frames or analytic")
    with torch.no_grad():
        a = model.at(t, with_velocity=True)
        v = a["velocities"]
        if velocity == "frames" and model.is_dynamic and len(times) > 1:
            dt = float(np.median(np.diff(np.asarray(times, np.float64))))
            t0, t1 = max(t - dt, lo), min(t + dt, hi)
            if t1 > t0:
                v = (model.at(t1)["means"] - model.at(t0)["means"]) / (t1 - t0)
    return State(positions=a["means"].numpy(), velocities=v.numpy(), source_index=np.arange(len(model)), time=t,
                 domain=domain_of(r, where))


# ---- the rest state ------------------------------------------------------------------------------
def kernel_for(solver: str):
    from ..sim.solvers import solver as solver_named

    return solver_named(solver).kernel


def rest_state(s: State, solver: str) -> tuple[float, float]:
    """(spacing, rest volume) of the particles for ``solver``: the one fixed by ``keep_rest_state``
    (before edits), else estimated from the particles as they are."""
    from ..sim.common import estimate_rest_state

    if s.rest is not None and s.rest[0] == solver:
        return s.rest[1], s.rest[2]
    return estimate_rest_state(s.positions, kernel_for(solver), "predict")


def keep_rest_state(s: State, solver: str) -> State:
    """Fix the particles' spacing and rest volume (per-particle mass) as they are now, before edits."""
    return replace(s, rest=(solver, *rest_state(s, solver)))


# ---- the continuation --------------------------------------------------------------------------------
def make_solver_for(s: State, solver: str, *, rest_density: float, viscosity: float = 0.0, device="cpu",
                    **overrides):
    from ..sim import Domain, solver_for_particles

    lo, hi = s.domain
    domain = Domain(tuple(map(float, lo)), tuple(map(float, hi)))
    return solver_for_particles(s.positions, domain, solver, rest_density=rest_density, viscosity=viscosity,
                                rest=rest_state(s, solver), device=device, **overrides)


def continue_state(s: State, *, frames: int, fps: float, solver: str = "pbf", rest_density: float = 1000.0,
                   viscosity: float = 0.0, out: Path | None = None, config: dict | None = None,
                   device: str = "cpu", progress=None, solver_settings: dict | None = None) -> tuple[SimData, dict]:
    """Simulate ``frames`` frames at ``fps`` from ``s``; frame k has time s.time + k / fps. With
    ``out``, each frame is written to that ``sim.h5`` as soon as it exists. Returns the SimData
    and a report (solver, estimated spacing and rest volume, steps, wall seconds).
    ``solver_settings``: DFSPHParams / PBFParams fields (e.g. ``{"iterations": 8}``)."""
    from ..sim import prepare_particles, run_frames

    if frames < 1:
        raise InputError("--frames", f"must be >= 1, got {frames}")
    if not fps > 0:
        raise InputError("--fps", f"must be a positive number, got {fps}")
    if len(s) < 2 and s.rest is None:
        raise InputError("predict", f"{len(s)} particle(s): too few to estimate a spacing")
    if len(s) == 0:
        raise InputError("predict", "no particle left to simulate")
    sol = make_solver_for(s, solver, rest_density=rest_density, viscosity=viscosity, device=device,
                          **(solver_settings or {}))
    x, v, prep = prepare_particles(s.positions, s.velocities, sol.domain, sol.spacing)
    report = {"solver": solver, "start_time_s": s.time, "spacing": sol.spacing, "rest_volume": sol.V,
              "particle_mass": sol.mass, "rest_density": rest_density, "viscosity": viscosity,
              "solver_settings": dict(solver_settings or {}), "edits": s.edits, **prep, **(config or {})}

    def make(positions, velocities, stats, times=None):
        return SimData(positions=positions, velocities=velocities, fps=fps, particle_radius=sol.spacing / 2,
                       rest_density=rest_density, viscosity=viscosity, gravity=tuple(map(float, sol.g.tolist())),
                       solver=solver, domain_min=tuple(sol.domain.lo), domain_max=tuple(sol.domain.hi),
                       scene="continuation", times=times, config=report, stats=stats, source_index=s.source_index)

    writer = None
    on_frame = None
    if out is not None:
        writer = SimWriter(out, make(np.zeros((1, len(s), 3)), np.zeros((1, len(s), 3)), {}), len(s), frames + 1)

        def on_frame(p, vel, k, m):
            writer.append(p, vel, s.time + k / fps, m)
    xt = torch.tensor(x, dtype=torch.float32, device=device)
    vt = torch.tensor(v, dtype=torch.float32, device=device)
    wall0 = time.perf_counter()
    try:
        res = run_frames(sol, xt, vt, fps=fps, seconds=frames / fps, progress=progress, on_frame=on_frame)
    except BaseException:
        if writer is not None:
            writer.close(complete=False, config={**report, "stopped_after_frames": writer.frames})
        raise
    report.update(steps=len(res.steps), wall_seconds=time.perf_counter() - wall0)
    if writer is not None:
        writer.close(complete=True, config=report)
    times = s.time + np.arange(len(res.positions)) / fps
    return make(np.stack(res.positions), np.stack(res.velocities), res.stats, times), report


__all__ = ["State", "state_at", "keep_rest_state", "rest_state", "continue_state", "make_solver_for"]
