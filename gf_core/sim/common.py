"""Pieces every particle solver shares: the box domain and its wall particles, lattice rest
volumes, the independent density/energy measurement, XSPH and implicit viscosity, the
safety net (box clamping, speed bound, NaN check) and the frame loop that logs error vs time.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import GFError, InputError
from ..sph.neighbors import neighbor_pairs
from ..sph import kernels


def native_available() -> bool:
    from .. import native

    return native.available()


def pick_backend(solver: str, backend: str, device) -> bool:
    """Whether a solver runs its pair sums natively (``csrc/sim_cpu.cpp``): CPU tensors with the
    native extension built, unless ``backend`` is "torch" (the reference path, also the one for
    CUDA tensors); "native" where that is impossible is an error."""
    ok = torch.device(device).type == "cpu" and native_available()
    if backend == "native" and not ok:
        from .. import native

        raise InputError(solver, f"backend 'native' needs CPU tensors and the native extension "
                                 f"({native.unavailable_reason() or 'device ' + str(device)})")
    return ok and backend != "torch"


class SimulationError(GFError):
    """A simulation could not continue (the message says at which step and why)."""


@dataclass
class Domain:
    lo: tuple
    hi: tuple

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise InputError("domain", f"box corners must be 3 finite numbers each, got {self.lo}, {self.hi}")
        if np.any(hi <= lo):
            raise InputError("domain", f"box max {hi.tolist()} must exceed min {lo.tolist()} on every axis")
        self.lo, self.hi = tuple(lo.tolist()), tuple(hi.tolist())

    @property
    def height(self) -> float:
        return self.hi[2] - self.lo[2]


def lattice_volume(kernel, h: float, spacing: float) -> float:
    """Rest volume V = 1 / sum_j W(x_j) over a cubic lattice: interior particles of a lattice of
    that spacing are then exactly at rest density."""
    n = int(math.ceil(h / spacing)) + 1
    g = torch.arange(-n, n + 1, dtype=torch.float64) * spacing
    p = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return float(1.0 / kernel(p.norm(dim=-1), h).sum())


def estimate_rest_state(positions, kernel, where: str = "simulate", iterations: int = 4,
                        percentile: float = 90.0) -> tuple[float, float]:
    """Spacing and rest volume of an arbitrary particle set (e.g. a reconstruction), for a solver
    whose support is h = 2 x spacing. The rest volume V = 1 / n0, with n0 the median of
    sum_j W(r_ij, h) over the better-filled half of the particles (the interior; surface particles
    have fewer neighbours), so the interior of the given set is at rest density whatever its
    packing. The spacing is the lattice spacing with that same rest volume (a lattice of spacing d
    has V = c d^3, c = ``lattice_volume(W, 2, 1)``): the wall particles, laid on a lattice of that
    spacing, then have the fluid's density too. (The median nearest-neighbour distance, the first
    guess, is below the mean spacing of a disordered liquid; walls laid at it are too dense and
    throw the fluid off the floor.) Fixed point of d -> (V(h = 2 d) / c)^(1/3), a few
    rounds from the nearest-neighbour guess. Returns (spacing, V)."""
    x = torch.as_tensor(np.asarray(positions), dtype=torch.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 2:
        raise InputError(where, f"need (N >= 2, 3) positions to estimate a rest state, got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise InputError(where, "positions contain NaN or infinite values")
    span = float((x.max(0).values - x.min(0).values).max())
    radius = max(span, 1e-6)
    for _ in range(30):  # grow until most particles have a neighbour
        i, j = neighbor_pairs(x, radius * 0.05)
        if i.numel() >= x.shape[0]:
            break
        radius *= 2
    d = (x[i] - x[j]).norm(dim=-1)
    nn = torch.full((x.shape[0],), float("inf"), dtype=torch.float64).scatter_reduce(0, i, d, "amin")
    nn = nn[torch.isfinite(nn) & (nn > 0)]
    if nn.numel() == 0:
        raise InputError(where, "particles are all coincident or isolated; cannot estimate a spacing")
    spacing = float(nn.median())
    c = lattice_volume(kernel, 2.0, 1.0)

    def rest_volume(sp):
        h = 2.0 * sp
        i, j = neighbor_pairs(x, h)
        dens = kernel(torch.zeros(x.shape[0], dtype=torch.float64), h)
        dens.index_add_(0, i, kernel((x[i] - x[j]).norm(dim=-1), h))
        return 1.0 / float(np.percentile(dens.numpy(), percentile))

    for _ in range(iterations):
        spacing = (rest_volume(spacing) / c) ** (1.0 / 3.0)
    return spacing, rest_volume(spacing)


def box_wall_particles(domain: Domain, spacing: float, layers: int, dtype=torch.float32, device=None):
    """Lattice particles filling a shell of ``layers`` layers outside the box (all six sides), the
    continuation of an interior fluid lattice, so that fluid next to a wall sees a full kernel."""
    lo, hi = np.asarray(domain.lo), np.asarray(domain.hi)
    axes = []
    for a in range(3):
        n = int(math.floor((hi[a] - lo[a]) / spacing + 1e-9))
        start = lo[a] + 0.5 * (hi[a] - lo[a] - (n - 1) * spacing)  # centred like the fluid lattices
        axes.append(start + spacing * np.arange(-layers, n + layers))
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.all((P > lo) & (P < hi), axis=1)
    return torch.as_tensor(P[~inside], dtype=dtype, device=device)


def enforce_box(x: torch.Tensor, v: torch.Tensor, domain: Domain, margin: float):
    """Bring positions back into the box (shrunk by ``margin``) by mirroring the overshoot at the
    face, and remove velocity into the walls. Mirroring, not clamping: particles clamped onto the
    same face line or corner become coincident, and coincident particles have no pressure gradient
    to separate them (a cluster of them then moves as one). Returns the number of particles moved."""
    lo = torch.tensor(domain.lo, dtype=x.dtype, device=x.device) + margin
    hi = torch.tensor(domain.hi, dtype=x.dtype, device=x.device) - margin
    below, above = x < lo, x > hi
    n = int((below | above).any(1).sum())
    if n:
        mirrored = torch.where(below, 2 * lo - x, torch.where(above, 2 * hi - x, x))
        x.copy_(torch.maximum(torch.minimum(mirrored, hi), lo))
        v.copy_(torch.where(below, v.clamp_min(0.0), torch.where(above, v.clamp_max(0.0), v)))
    return n


def even_step(dt: float, remaining: float) -> float:
    """A step no larger than ``dt`` that divides ``remaining`` (the time to the next frame) evenly,
    so that no sliver step is ever taken: a pressure solve over a tiny dt would try to undo the
    whole density error in that instant and blow the velocities up."""
    if remaining <= dt:
        return remaining
    return remaining / math.ceil(remaining / dt - 1e-9)


def limit_speed(v: torch.Tensor, vmax: float) -> int:
    s = v.norm(dim=-1)
    over = s > vmax
    n = int(over.sum())
    if n:
        v.mul_(torch.where(over, vmax / s.clamp_min(1e-30), torch.ones_like(s))[:, None])
    return n


def check_finite(step: int, t: float, **tensors) -> None:
    for name, tt in tensors.items():
        if not torch.isfinite(tt).all():
            raise SimulationError(f"step {step} (t = {t:.5f} s): {name} became NaN/inf; "
                                  "reduce the time step (cfl / dt_max) or stiffness")


def xsph(v, i, j, r, V, h, c: float, kernel: kernels.Kernel = kernels.CUBIC):
    """XSPH velocity smoothing: v_i += c sum_j V (v_j - v_i) W_ij (Monaghan 1989)."""
    if c == 0.0 or i.numel() == 0:
        return v
    w = (V * c) * kernel.W(r, h)
    dv = torch.zeros_like(v).index_add_(0, i, (v[j] - v[i]) * w[:, None])
    return v + dv


VISCOSITY_BOUNDARIES = ("free-slip", "no-slip")


def implicit_viscosity(v, x, i, j, bi, bb, xb, V, h, nu_dt: float, *, boundary: str = "free-slip",
                       max_iters: int = 50, tol: float = 1e-4, kernel: kernels.Kernel = kernels.CUBIC,
                       lists=None):
    """Solve (I - nu dt L) v_new = v with conjugate gradients, L the SPH Laplacian of Weiler et al.
    2018: (L v)_i = 10 sum_j V ((v_i - v_j) . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij.
    ``boundary``: "free-slip" (default, as SPlisHSPlasH's default) leaves the walls out of the
    viscosity, so a fluid slides along them; "no-slip" adds the same term with the wall particles
    at rest, which brakes every particle near a wall (the falling sphere's splash with either:
    BENCHMARKS.md, "Viscosity at the walls"). Unconditionally stable: honey-like
    viscosity needs no sub-stepping. ``lists``: the native CSR neighbour lists (rowptr, col,
    wall rowptr, wall col) of x, to apply the operator natively (the pair lists i, j, bi, bb are
    then not used). Returns (v_new, iterations)."""
    if boundary not in VISCOSITY_BOUNDARIES:
        raise InputError("viscosity", f"unknown viscosity boundary {boundary!r} ({', '.join(VISCOSITY_BOUNDARIES)})")
    if nu_dt == 0.0 or v.shape[0] == 0:
        return v, 0
    if lists is not None:
        from .. import native

        ext, (rowptr, col, browptr, bcol) = native.load(), lists
        kind = {"cubic": 0, "wendland": 1}[kernel.name]

        def A(u):  # (I - nu dt L) u, natively
            return ext.viscosity_apply(u.contiguous(), x, xb, rowptr, col, browptr, bcol, V, h, nu_dt,
                                       boundary == "no-slip", kind)
    else:
        if boundary == "free-slip":
            bi, bb = bi[:0], bb[:0]
        d = x[i] - x[j]
        r = d.norm(dim=-1)
        g = kernel.grad(d, r, h)
        coef = 10.0 * V / (r * r + 0.01 * h * h)
        db = x[bi] - xb[bb]
        rb = db.norm(dim=-1)
        gb = kernel.grad(db, rb, h)
        coef_b = 10.0 * V / (rb * rb + 0.01 * h * h)

        def A(u):  # (I - nu dt L) u
            Lu = torch.zeros_like(u)
            Lu.index_add_(0, i, (coef * ((u[i] - u[j]) * d).sum(-1))[:, None] * g)
            if bi.numel():
                Lu.index_add_(0, bi, (coef_b * (u[bi] * db).sum(-1))[:, None] * gb)
            return u - nu_dt * Lu

    sol = v.clone()
    res = v - A(sol)
    p = res.clone()
    rs = (res * res).sum()
    b2 = (v * v).sum().clamp_min(1e-30)
    it = 0
    while it < max_iters and rs > tol * tol * b2:
        Ap = A(p)
        alpha = rs / (p * Ap).sum().clamp_min(1e-30)
        sol = sol + alpha * p
        res = res - alpha * Ap
        rs_new = (res * res).sum()
        p = res + (rs_new / rs.clamp_min(1e-30)) * p
        rs = rs_new
        it += 1
    return sol, it


@dataclass
class Measure:
    """Independent measurement of a state (not the solver's residual): densities recomputed from
    the positions with the solver's kernel (support 4 r) and its lattice rest volume, wall
    particles included."""

    h: float
    V: float
    wall: torch.Tensor
    gravity: torch.Tensor
    z0: float
    mass: float
    kernel: kernels.Kernel = kernels.CUBIC
    _wall_grid: list | None = field(default=None, init=False, repr=False)  # the walls' native grid, built once

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """sum_j W(x_i - x_j) over fluid and wall particles, self included (native on CPU)."""
        n = x.shape[0]
        rho = torch.full((n,), self.kernel.zero(self.h), dtype=x.dtype, device=x.device)
        kind = {"cubic": 0, "wendland": 1}.get(self.kernel.name)
        if kind is not None and x.device.type == "cpu" and native_available():
            from ..sph.neighbors import build_grid
            from .. import native

            ext, xc = native.load(), x.contiguous()
            rho += ext.kernel_sum(xc, xc, [], self.h, kind, True)
            if self.wall.numel():
                if self._wall_grid is None:
                    self._wall_grid = build_grid(self.wall, self.h)
                rho += ext.kernel_sum(xc, self.wall, self._wall_grid, self.h, kind, False)
            return rho
        i, j = neighbor_pairs(x, self.h)
        W = self.kernel.W
        rho.index_add_(0, i, W((x[i] - x[j]).norm(dim=-1), self.h))
        if self.wall.numel():
            bi, bb = neighbor_pairs(x, self.h, self.wall)
            rho.index_add_(0, bi, W((x[bi] - self.wall[bb]).norm(dim=-1), self.h))
        return rho

    def __call__(self, x: torch.Tensor, v: torch.Tensor) -> dict:
        n = x.shape[0]
        if n == 0:
            return {"density_err_mean": 0.0, "density_err_max": 0.0, "kinetic": 0.0, "potential": 0.0}
        rho = self.density(x)
        err = (rho * self.V - 1.0).clamp_min(0.0)  # compression (free-surface deficit is not error)
        kin = 0.5 * self.mass * float((v * v).sum())
        pot = -self.mass * float(((x - x.new_tensor([0, 0, self.z0])) @ self.gravity.to(x)).sum())
        return {"density_err_mean": float(err.mean()), "density_err_max": float(err.max()),
                "kinetic": kin, "potential": pot}


class SolverBase:
    """What DFSPH and PBF share: the particle lattice (spacing 2r, support h = 4r), the rest volume
    V and mass, the wall particles, gravity, the speed safety net and the independent measure.
    ``rest_volume(h, spacing)`` gives the solver's V; ``kernel`` is the one the measurement (and
    XSPH) uses; ``measure_scale`` maps its lattice volume to the same rest state (1 unless V was
    estimated from data)."""

    def __init__(self, params, domain: Domain, rest_volume, *, device="cpu", dtype=torch.float32,
                 measure_scale: float = 1.0, kernel: kernels.Kernel = kernels.CUBIC):
        params.validate()
        self.p, self.domain, self.kernel = params, domain, kernel
        r = params.particle_radius
        self.spacing = 2.0 * r
        self.h = 4.0 * r
        self.V = rest_volume(self.h, self.spacing)
        self.mass = params.rest_density * self.V
        self.wall = box_wall_particles(domain, self.spacing, layers=2, dtype=dtype, device=device)
        self.g = torch.tensor(params.gravity, dtype=dtype, device=device)
        # Force limit on the step (Monaghan 1992), dt <= force_cfl sqrt(2r / |g|): at rest the CFL
        # limit is void and dt would jump to its cap, which a resting tank does not survive
        # (BENCHMARKS.md, "Hydrostatic tank").
        gnorm = float(self.g.norm())
        self.dt_force = params.force_cfl * math.sqrt(self.spacing / gnorm) if gnorm > 0 else math.inf
        self.vmax = params.max_speed or 2.0 * math.sqrt(2.0 * max(gnorm, 1e-3) * domain.height) + 1.0
        self.measure = Measure(h=self.h, V=lattice_volume(kernel.W, self.h, self.spacing) * measure_scale,
                               wall=self.wall, gravity=self.g, z0=domain.lo[2], mass=self.mass,
                               kernel=kernel)

    def reset(self):
        """Forget what the solver carries from step to step (warm starts); called after ``settle``."""

    def resume_state(self) -> dict:
        """What the solver carries from step to step, as numpy arrays (saved with each frame of a
        ``sim.h5`` being written, so that a killed run resumes to the uninterrupted result)."""
        return {}

    def load_resume_state(self, state: dict) -> None:
        """Take back what ``resume_state`` gave."""


@dataclass
class FrameResult:
    positions: list = field(default_factory=list)
    velocities: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    steps: list = field(default_factory=list)  # per-step log: t, wall_s, dt, iterations, errors


def settle(solver, x: torch.Tensor, v: torch.Tensor, *, seconds: float, damping: float = 0.05,
           jitter: float = 0.05, seed: int = 0) -> dict:
    """Bring a fluid to rest in its container before t = 0, in place: the lattice positions are
    jittered by up to ``jitter`` spacings (a lattice's free surface is an unstable equilibrium,
    which would otherwise give way only when round-off has grown, in the middle of the run), then
    the solver runs for ``seconds`` with the velocities damped after every step by a factor
    (1 - damping (1 - t / seconds)), annealed to no damping at the end, and finally the velocities
    and the solver's warm starts are reset. A lattice is not the packing a fluid at rest has:
    without settling, a lattice's top layer collapses in the first part of the run. The annealing
    matters: a state held by constant damping is not an equilibrium of the undamped solver, and
    released it moves again (BENCHMARKS.md, "Hydrostatic tank").
    Returns a log: steps, wall seconds, the fastest particle before the reset and the mean density
    error of the settled state."""
    if not (math.isfinite(seconds) and seconds >= 0):
        raise InputError("settle", f"seconds must be >= 0, got {seconds}")
    if not 0 < damping < 1:
        raise InputError("settle", f"damping must be in (0, 1), got {damping}")
    wall0 = time.perf_counter()
    if jitter and x.shape[0]:
        gen = torch.Generator(device="cpu").manual_seed(seed)
        shift = (torch.rand(x.shape, generator=gen, dtype=torch.float64) * 2 - 1) * (jitter * solver.spacing)
        x.add_(shift.to(device=x.device, dtype=x.dtype))
        enforce_box(x, v, solver.domain, 0.0)
    t, steps = 0.0, 0
    while t < seconds - 1e-12:
        info = solver.step(x, v, seconds - t)
        t += info["dt"]
        v.mul_(1.0 - damping * max(1.0 - t / seconds, 0.0))
        steps += 1
        check_finite(steps, t, positions=x, velocities=v)
    speed = float(v.norm(dim=-1).max()) if x.shape[0] else 0.0
    v.zero_()
    solver.reset()
    return {"settle_seconds": seconds, "settle_steps": steps, "settle_final_speed": speed,
            "settle_density_err_mean": solver.measure(x, v)["density_err_mean"],
            "settle_wall_s": time.perf_counter() - wall0}


def run_frames(solver, x: torch.Tensor, v: torch.Tensor, *, fps: float, seconds: float,
               progress=None, measure_every_step: bool = True, on_frame=None, start_frame: int = 0) -> FrameResult:
    """Advance ``solver`` from t = 0 and record frames at k / fps. Logs, per step, the simulated
    time, wall-clock seconds, dt, solver iterations and the independently measured density error
    and energy, so that error can be plotted against run time. ``on_frame(positions, velocities,
    frame index, measures)`` is called with each recorded frame (numpy), e.g. to write it at once.
    ``start_frame`` k > 0: (x, v) is frame k's state (a resumed run), frames k + 1 on are recorded;
    each frame starts at exactly k / fps, so a resumed run steps as the uninterrupted one did."""
    if fps <= 0 or seconds < 0:
        raise InputError("simulate", f"fps must be positive and seconds non-negative (got {fps}, {seconds})")
    n_frames = int(round(seconds * fps)) + 1
    res = FrameResult()
    per_frame: dict[str, list] = {}

    def record_frame(m, k):
        res.positions.append(x.detach().cpu().numpy().copy())
        res.velocities.append(v.detach().cpu().numpy().copy())
        for key, val in m.items():
            per_frame.setdefault(key, []).append(val)
        if on_frame is not None:
            on_frame(res.positions[-1], res.velocities[-1], k, m)

    if start_frame == 0:
        record_frame(solver.measure(x, v), 0)
    step = 0
    wall0 = time.perf_counter()
    for f in range(start_frame + 1, n_frames):
        t, t_end = (f - 1) / fps, f / fps
        while t < t_end - 1e-12:
            dt_max = t_end - t
            info = solver.step(x, v, dt_max)
            t += info["dt"]
            step += 1
            check_finite(step, t, positions=x, velocities=v)
            entry = {"t": t, "wall_s": time.perf_counter() - wall0, **info}
            if measure_every_step:
                entry.update(solver.measure(x, v))
            res.steps.append(entry)
        record_frame(res.steps[-1] if measure_every_step and res.steps else solver.measure(x, v), f)
        if progress:
            progress(f, n_frames - 1, t, res.steps[-1] if res.steps else {})
    keys = ("density_err_mean", "density_err_max", "kinetic", "potential")
    res.stats = {k: np.asarray([pf for pf in per_frame.get(k, [])], np.float64) for k in keys}
    return res
