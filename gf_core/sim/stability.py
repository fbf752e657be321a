"""The stability suite: stiff and extreme cases every solver must survive with a finite state
inside the box, or refuse with a clear error before starting. Used by the tests and by
``gf-cli bench sim --stability``."""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ..errors import GFError
from . import initial_state, make_solver, prepare_particles, run_frames

CASES = ("hydrostatic", "large_dt", "large_dt_at_rest", "high_viscosity", "stiff", "coincident", "isolated",
         "outside_box", "one_particle", "zero_particles")


def setup_case(case: str, solver: str, particles: int):
    """The start of one case: (scene, positions, velocities, particle radius, solver overrides)."""
    overrides: dict = {}
    scene = "dam_break"
    if case == "hydrostatic":
        scene = "hydrostatic_tank"
    elif case == "large_dt":  # a step cap 10x the default: the CFL limit must take over
        overrides = {"dt_max": 0.05} if solver == "dfsph" else {"dt": 1.0 / 24.0}
    elif case == "large_dt_at_rest":  # the same cap on water at rest: no CFL limit applies
        scene = "hydrostatic_tank"
        overrides = {"dt_max": 0.05} if solver == "dfsph" else {"dt": 1.0 / 24.0}
    elif case == "high_viscosity":
        scene = "honey_cone"
        overrides = {"viscosity": 10.0}
    elif case == "stiff":
        overrides = ({"density_tol": 1e-6, "divergence_tol": 1e-6, "max_iterations": 300}
                     if solver == "dfsph" else {"iterations": 40, "relaxation": 1e-5})
    sc, x, v, radius = initial_state(scene, particles=particles)
    rng = np.random.default_rng(1)
    if case == "coincident":  # a tenth of the particles duplicated exactly onto others
        k = max(1, x.shape[0] // 10)
        x = np.concatenate([x, x[rng.choice(x.shape[0], k, replace=False)]])
        v = np.zeros_like(x)
    elif case == "isolated":
        x = np.concatenate([x, [[0.9, 0.05, 0.5]]]).astype(np.float32)
        v = np.zeros_like(x)
    elif case == "outside_box":
        x = x.copy()
        x[::2] += np.array([0.0, 0.5, 1.0], np.float32)  # half of them start above/behind the box
    elif case == "one_particle":
        x, v = np.array([[0.5, 0.05, 0.5]], np.float32), np.zeros((1, 3), np.float32)
    elif case == "zero_particles":
        x, v = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    return sc, x, v, radius, overrides


def run_case(case: str, solver: str, *, particles: int = 600, seconds: float = 0.25,
             fps: float = 20.0) -> dict:
    """Run one case; returns a record with ``ok`` True when the run ended finite and inside the
    box, or refused up front with a clear error (``refused``)."""
    if case not in CASES:
        raise ValueError(f"unknown stability case {case!r}; choose from {', '.join(CASES)}")
    sc, x, v, radius, overrides = setup_case(case, solver, particles)
    rec = {"case": case, "solver": solver, "scene": sc.name, "particles": int(x.shape[0]),
           "overrides": overrides}
    t0 = time.perf_counter()
    try:
        s = make_solver(solver, radius, sc.domain, sc.material_params, **overrides)
        x, v, report = prepare_particles(x, v, sc.domain, 2 * radius)
    except GFError as e:
        rec.update(ok=True, refused=str(e), wall_s=time.perf_counter() - t0)
        return rec
    xt, vt = torch.tensor(x, dtype=torch.float32), torch.tensor(v, dtype=torch.float32)
    res = run_frames(s, xt, vt, fps=fps, seconds=seconds)
    lo, hi = torch.tensor(sc.domain.lo), torch.tensor(sc.domain.hi)
    finite = bool(torch.isfinite(xt).all() and torch.isfinite(vt).all())
    inside = bool(((xt >= lo - 1e-6) & (xt <= hi + 1e-6)).all())
    speed = float(vt.norm(dim=-1).max())
    g = math.sqrt(9.81 * sc.domain.height)
    rec.update(ok=finite and inside, finite=finite, inside=inside, max_speed=speed,
               max_speed_rel=speed / g, density_err_mean=float(res.stats["density_err_mean"][-1]),
               steps=len(res.steps), wall_s=time.perf_counter() - t0, **report)
    return rec
