"""Particle simulators: DFSPH and PBF, scene presets, and ``simulate`` which writes ``SimData``.

Every solver logs, per step, its error next to wall-clock time (``FrameResult.steps``), which
``gf-cli bench sim`` turns into tables and error-vs-seconds plots.
"""

from __future__ import annotations

import json

import numpy as np
import torch

from ..errors import InputError
from ..formats.hdf5 import SimData, SimWriter, read_sim
from .common import Domain, FrameResult, SimulationError, run_frames, settle
from .dfsph import DFSPH, DFSPHParams
from .pbf import PBF, PBFParams
from .scenes import SCENES, initial_state, presets
from .solvers import SOLVERS, make_solver, solver



def prepare_particles(x: np.ndarray, v: np.ndarray, domain: Domain, spacing: float, *,
                      outside: str = "clamp", seed: int = 0):
    """Validate and tidy initial particles: reject NaN and empty sets; bring particles outside
    the box inside (``outside="clamp"``) or refuse (``"error"``); separate exactly coincident
    particles by a deterministic 1e-3 x spacing jitter (their pressure gradient has no direction).
    Returns (x, v, report)."""
    x = np.asarray(x, np.float64).reshape(-1, 3)
    v = np.asarray(v, np.float64).reshape(-1, 3)
    if x.shape[0] == 0:
        raise InputError("simulate", "no particles to simulate")
    if v.shape != x.shape:
        raise InputError("simulate", f"velocities {v.shape} must match positions {x.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        raise InputError("simulate", "initial positions or velocities contain NaN or infinite values")
    lo, hi = np.asarray(domain.lo), np.asarray(domain.hi)
    margin = 0.5 * spacing
    out = np.any((x < lo) | (x > hi), axis=1)
    if out.any() and outside == "error":
        raise InputError("simulate", f"{int(out.sum())} particles start outside the box {domain.lo}..{domain.hi}")
    if outside not in ("clamp", "error"):
        raise InputError("simulate", f"unknown outside policy {outside!r} (clamp, error)")
    x = np.clip(x, lo + np.minimum(margin, (hi - lo) / 2), hi - np.minimum(margin, (hi - lo) / 2))
    _, first, counts = np.unique(np.round(x / (1e-6 * spacing)).astype(np.int64), axis=0,
                                 return_index=True, return_counts=True)
    dup = np.ones(x.shape[0], bool)
    dup[first] = False
    if dup.any():
        rng = np.random.default_rng(seed)
        x[dup] += rng.normal(scale=1e-3 * spacing, size=(int(dup.sum()), 3))
        x = np.clip(x, lo, hi)
    return x, v, {"outside_moved": int(out.sum()), "coincident_separated": int(dup.sum())}


def solver_for_particles(positions, domain: Domain, name: str, *, rest_density: float = 1000.0,
                         viscosity: float = 0.0, rest: tuple | None = None, device="cpu", where: str = "predict",
                         **overrides):
    """Solver ``name`` for an arbitrary particle set (a reconstruction's) in ``domain``: its spacing
    and rest volume are ``rest`` = (spacing, V) when given, else estimated from the particles
    (``estimate_rest_state``: the interior at rest density whatever its packing); XSPH as the
    simulate presets use for water."""
    from .common import estimate_rest_state
    from .scenes import MATERIALS

    entry = solver(name)
    spacing, V = rest if rest is not None else estimate_rest_state(positions, entry.kernel, where)
    overrides = {"xsph": MATERIALS["water"]["xsph"], **overrides}
    return entry.cls(entry.params(particle_radius=spacing / 2.0, rest_density=rest_density, rest_volume=V,
                                  viscosity=viscosity, **overrides), domain, device=device)


def simulate(scene: str, *, solver: str = "dfsph", particles: int | None = None,
             spacing: float | None = None, fps: float | None = None, seconds: float | None = None,
             device: str = "cpu", progress=None, settle_seconds: float | None = None,
             settle_seed: int = 0, out=None, resume: bool = True, **overrides) -> tuple[SimData, FrameResult]:
    """Run a preset scene and return (SimData for sim.h5, the per-step log). ``settle_seconds``
    (default: the scene's, ``Scene.settle``) of damped settling run before t = 0, from the start
    lattice jittered with ``settle_seed``. With ``out`` (a path) every frame is written to that
    ``sim.h5`` as soon as it is computed, with the solver's state beside the last one
    (``SimWriter``): an interrupted run leaves the frames so far in a file marked incomplete, and
    the same call again (``resume``) goes on from its last frame to what the uninterrupted run
    gives; a file of other settings is started afresh."""
    sc, x, v, radius = initial_state(scene, particles=particles, spacing=spacing)
    fps = sc.fps if fps is None else fps
    seconds = sc.seconds if seconds is None else seconds
    settle_seconds = sc.settle if settle_seconds is None else settle_seconds
    s = make_solver(solver, radius, sc.domain, sc.material_params, device=device, **overrides)
    frames_expected = int(round(seconds * fps)) + 1
    request = {"scene": scene, "solver": solver, "particles": particles, "spacing": spacing, "fps": fps,
               "seconds": seconds, "settle_seconds": settle_seconds, "settle_seed": settle_seed,
               "device": str(device), "overrides": {k: overrides[k] for k in sorted(overrides)}}

    def make(positions, velocities, stats, config):
        return SimData(positions=positions, velocities=velocities, fps=fps, particle_radius=radius,
                       rest_density=sc.material_params["rest_density"], viscosity=sc.material_params["viscosity"],
                       gravity=tuple(float(g) for g in s.g.tolist()), solver=solver, domain_min=sc.domain.lo,
                       domain_max=sc.domain.hi, scene=scene, config=config, stats=stats)

    writer = _resumable(out, request, x.shape[0]) if out is not None and resume else None
    if writer is not None:  # frame k's state and the solver's warm starts, as the killed run had them
        p, vel, state = writer.resume_state()
        start = writer.frames - 1
        cfg = read_sim_config(writer)
        xt = torch.tensor(p, dtype=torch.float32, device=device)
        vt = torch.tensor(vel, dtype=torch.float32, device=device)
        s.load_resume_state(state)
    else:
        start = 0
        x, v, report = prepare_particles(x, v, sc.domain, 2 * radius)
        xt = torch.tensor(x, dtype=torch.float32, device=device)
        vt = torch.tensor(v, dtype=torch.float32, device=device)
        if settle_seconds:
            report.update(settle(s, xt, vt, seconds=settle_seconds, seed=settle_seed), settle_seed=settle_seed)
        cfg = {"scene": scene, "solver": solver, "spacing": 2 * radius, "device": device,
               "material": sc.material, **{k: v for k, v in overrides.items()}, **report, "request": request}
        if out is not None:
            header = make(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), {}, cfg)
            writer = SimWriter(out, header, x.shape[0], frames_expected)

    on_frame = None
    if writer is not None:
        def on_frame(p, vel, k, m):
            writer.append(p, vel, k / fps, m, solver_state=s.resume_state())
    try:
        res = run_frames(s, xt, vt, fps=fps, seconds=seconds, progress=progress, on_frame=on_frame,
                         start_frame=start)
    except BaseException:
        if writer is not None:
            writer.close(complete=False, config={**cfg, "stopped_after_frames": writer.frames})
        raise
    cfg.update(steps=len(res.steps), wall_seconds=res.steps[-1]["wall_s"] if res.steps else 0.0)
    cfg.pop("stopped_after_frames", None)
    if start:
        cfg["resumed_after_frame"] = start
    if writer is not None:
        writer.close(complete=True, config=cfg)
    if start:
        return read_sim(out), res
    sim = make(np.stack(res.positions), np.stack(res.velocities), res.stats, cfg)
    return sim, res


def _resumable(out, request: dict, n_particles: int):
    """A writer going on with ``out`` when it is an incomplete run of ``request``, else None."""
    from pathlib import Path

    if not Path(out).is_file():
        return None
    w = SimWriter.reopen(out, n_particles)
    if w is None:
        return None
    if read_sim_config(w).get("request") != json.loads(json.dumps(request)):
        w.close(complete=False)
        return None
    return w


def read_sim_config(writer) -> dict:
    """The config dict of the file a ``SimWriter`` holds open."""
    try:
        cfg = json.loads(writer.f.attrs["config"])
    except (KeyError, TypeError, ValueError):
        return {}
    return cfg if isinstance(cfg, dict) else {}


__all__ = ["simulate", "make_solver", "solver_for_particles", "prepare_particles",
           "DFSPH", "DFSPHParams", "PBF", "PBFParams",
           "Domain", "SimulationError", "SCENES", "SOLVERS", "solver", "presets", "initial_state", "run_frames",
           "settle"]
