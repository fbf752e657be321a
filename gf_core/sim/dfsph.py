"""Divergence-free SPH (Bender & Koschier 2015; 2017 Alg. 1-3), in normalised densities
rho~ = rho / rho0 and rest volumes V = m / rho0.

One step, read top to bottom in ``step``:
  1. time step: the CFL limit dt = cfl * 2r / max|v| and the force limit
     dt = force_cfl * sqrt(2r / |g|) (Monaghan 1992), clamped to [dt_min, dt_max] and the frame end
  2. non-pressure forces: gravity, XSPH smoothing, implicit viscosity      -> v*
  3. constant-density solve (Jacobi on kappa >= 0, warm-started with half the last kappa):
        v        = v* - dt [sum_j V (kappa_i + kappa_j) gradW_ij + sum_b V (kappa_i + kappa_b) gradW_ib]
        rho~*_i  = rho~_i + dt [sum_j V (v_i - v_j) . gradW_ij + sum_b V v_i . gradW_ib]
        rho~*_b  = rho~_b + dt  sum_i V v_i . gradW_ib                       (wall particle b)
        kappa_k += max(rho~*_k - 1, 0) alpha_k / dt^2      for fluid and wall particles k,
     until the compression sum_k max(rho~*_k - 1, 0) / N_fluid < density_tol;
     alpha_i = 1 / (|g_f + g_b|^2 + sum_j |V gradW_ij|^2), g_f = sum_j V gradW_ij,
     g_b = sum_b V gradW_ib, and alpha_b = 1 / sum_i |V gradW_ib|^2 capped at 4x a full-lattice
     fluid particle's alpha (a wall particle with few fluid neighbours over-corrects in Jacobi).
  4. x += dt v (box mirror as a safety net); neighbours, densities and alpha at the new positions
  5. divergence-free solve: the same iteration with residual dt * D rho~_k / Dt, until its mean
     is below divergence_tol (particles with < 20 neighbours are skipped).

Walls are lattice particles continuing the fluid lattice outside the box (``common``). Each wall
particle carries a density constraint rho~_b <= 1 and its own pressure-like unknown kappa_b,
solved with the fluid's (pressure boundaries, Band et al. 2018): the velocity change is then
-dt D^T kappa, the transpose of the divergence operator D that the residual uses, so the pressure
solve is a projection and cannot add energy. With kappa_b extrapolated from the fluid instead
(Adami et al. 2012) the two operators differ and a tank at rest gained energy: its centre of mass
rose, and after 2 s at rest its fastest particle grew again to 2.7-3.2% of sqrt(gH) by 4 s; with
wall unknowns it stays at or below 0.5% from 2 s to 5 s, the energy only falls, the dam-break
front is unchanged (within 3%) and the density solve needs 23 instead of 20.5 iterations per
step (BENCHMARKS.md, "Hydrostatic tank", item 8).
Kernel: Wendland C2 with support 4r (``kernels.WENDLAND``) for densities, gradients, XSPH and
viscosity. With the cubic spline a fluid lattice under hydrostatic pressure is unstable (its
speed grows ten-fold per 0.1 s from round-off) and rearranges into a glass; with Wendland C2 it
stays at rest (BENCHMARKS.md, "Hydrostatic tank").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..sph.neighbors import build_grid, neighbor_lists, neighbor_pairs
from ..sph import kernels
from .common import (VISCOSITY_BOUNDARIES, Domain, SolverBase, enforce_box, estimate_rest_state, even_step,
                     implicit_viscosity, lattice_volume, limit_speed, pick_backend, xsph)


WALL_ALPHA_CAP = 4.0  # wall factor alpha_b <= 4 x a full-lattice fluid particle's (see _neighbourhood)
DIVERGENCE_MIN_NEIGHBOURS = 20  # fewer (fluid + wall): no divergence estimate (see _residuals)


@dataclass
class DFSPHParams:
    particle_radius: float
    rest_density: float = 1000.0
    gravity: tuple = (0.0, 0.0, -9.81)
    cfl: float = 0.4
    force_cfl: float = 0.15        # dt <= force_cfl sqrt(2r / |g|): a fluid at rest has no CFL limit
    dt_min: float = 1e-5
    dt_max: float = 5e-3
    density_tol: float = 1e-4      # 0.01 % mean compression
    divergence_tol: float = 1e-3   # 0.1 % per step
    min_iterations: int = 2
    max_iterations: int = 100
    xsph: float = 0.01             # XSPH smoothing (water)
    viscosity: float = 0.0         # kinematic viscosity nu [m^2/s], solved implicitly
    viscosity_boundary: str = "free-slip"  # or "no-slip": the walls' friction (common.implicit_viscosity)
    max_speed: float | None = None  # safety net; default from the domain height
    rest_volume: float | None = None  # V = 1 / n0; None: from a lattice of spacing 2 r
    backend: str = "auto"          # pair sums: "native" (C++, CPU), "torch" (reference), "auto"

    def validate(self):
        from ..errors import InputError

        for k in ("particle_radius", "rest_density", "cfl", "force_cfl", "dt_min", "dt_max",
                  "density_tol", "divergence_tol"):
            val = getattr(self, k)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise InputError("dfsph", f"{k} must be a positive number, got {val!r}")
        if self.cfl > 1.0:
            raise InputError("dfsph", f"cfl {self.cfl} > 1: particles would cross more than a particle "
                                      "diameter per step; use cfl <= 1 (default 0.4) and raise dt_max instead")
        if self.dt_min > self.dt_max:
            raise InputError("dfsph", f"dt_min {self.dt_min} > dt_max {self.dt_max}")
        if not 0 <= self.xsph <= 1:
            raise InputError("dfsph", f"xsph must be in [0, 1], got {self.xsph}")
        if self.viscosity_boundary not in VISCOSITY_BOUNDARIES:
            raise InputError("dfsph", f"unknown viscosity_boundary {self.viscosity_boundary!r} "
                                   f"({', '.join(VISCOSITY_BOUNDARIES)})")
        if not (math.isfinite(self.viscosity) and self.viscosity >= 0):
            raise InputError("dfsph", f"viscosity must be >= 0, got {self.viscosity}")
        if self.rest_volume is not None and not (math.isfinite(self.rest_volume) and self.rest_volume > 0):
            raise InputError("dfsph", f"rest_volume must be a positive number, got {self.rest_volume}")
        if self.backend not in ("auto", "native", "torch"):
            raise InputError("dfsph", f"unknown backend {self.backend!r} (auto, native, torch)")


class DFSPH(SolverBase):
    name = "dfsph"

    def __init__(self, params: DFSPHParams, domain: Domain, *, device="cpu", dtype=torch.float32):
        r = params.particle_radius
        lattice_V = lattice_volume(kernels.WENDLAND.W, 4.0 * r, 2.0 * r) if r > 0 and math.isfinite(r) else 1.0
        super().__init__(params, domain, lambda h, d: params.rest_volume or lattice_V,
                         device=device, dtype=dtype, kernel=kernels.WENDLAND,
                         measure_scale=(params.rest_volume or lattice_V) / lattice_V)
        self.warm = 0.5  # warm start: half the previous step's kappa (as SPlisHSPlasH does)
        self.margin = 0.1 * self.spacing  # the box mirror is only a safety net: walls hold the fluid
        self._kappa = self._kappa_v = None
        self._cache = None  # neighbours/densities/alpha of the current positions
        self._wall_static = None
        self.native = pick_backend("dfsph", params.backend, device)
        self._wall_grid = None
        # alpha of a particle inside a full lattice (g_f = 0): 1 / sum_j |V gradW_ij|^2
        m = int(math.ceil(self.h / self.spacing))
        g = torch.arange(-m, m + 1, dtype=torch.float64) * self.spacing
        P = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        gl = self.V * self.kernel.grad(P, P.norm(dim=-1).clamp_min(1e-12), self.h)
        self._alpha_lattice = float(1.0 / (gl ** 2).sum())

    @classmethod
    def from_positions(cls, positions, domain: Domain, *, rest_density: float = 1000.0, device="cpu",
                       dtype=torch.float32, **overrides) -> "DFSPH":
        """A DFSPH solver for an arbitrary particle set (``common.estimate_rest_state``)."""
        spacing, V = estimate_rest_state(positions, kernels.WENDLAND.W, "dfsph")
        params = DFSPHParams(particle_radius=spacing / 2.0, rest_density=rest_density, rest_volume=V,
                             **overrides)
        return cls(params, domain, device=device, dtype=dtype)

    def reset(self):
        self._kappa = self._kappa_v = None

    def resume_state(self) -> dict:
        """The warm starts of the two pressure solves."""
        return {k: getattr(self, "_" + k).detach().cpu().numpy() for k in ("kappa", "kappa_v")
                if getattr(self, "_" + k) is not None}

    def load_resume_state(self, state: dict) -> None:
        dev = self.wall.device
        for k in ("kappa", "kappa_v"):
            setattr(self, "_" + k, torch.as_tensor(state[k], device=dev) if k in state else None)

    # ---- density and the DFSPH factor -------------------------------------------------------------
    def _wall_self(self):
        """Density and neighbour count of each wall particle from the other wall particles (static)."""
        if self._wall_static is None:
            h, V, K, w = self.h, self.V, self.kernel, self.wall
            wi, wj = neighbor_pairs(w, h) if w.numel() else (torch.zeros(0, dtype=torch.long),) * 2
            rho = torch.full((w.shape[0],), V * K.zero(h), dtype=w.dtype, device=w.device)
            rho.index_add_(0, wi, V * K.W((w[wi] - w[wj]).norm(dim=-1), h))
            self._wall_static = (rho, torch.bincount(wi, minlength=w.shape[0]))
        return self._wall_static

    def _neighbourhood(self, x):
        if self.native:
            return self._neighbourhood_native(x)
        h, V, K = self.h, self.V, self.kernel
        n, nw = x.shape[0], self.wall.shape[0]
        i, j = neighbor_pairs(x, h)
        bi, bb = neighbor_pairs(x, h, self.wall) if nw else (i[:0], j[:0])
        d = x[i] - x[j]
        r = d.norm(dim=-1)
        gw = V * K.grad(d, r, h)                    # V gradW_ij
        db = x[bi] - self.wall[bb]
        rb = db.norm(dim=-1)
        gwb = V * K.grad(db, rb, h)                 # V gradW_ib (gradient at the fluid particle)
        rho = torch.full((n,), V * K.zero(h), dtype=x.dtype, device=x.device)
        rho.index_add_(0, i, V * K.W(r, h))
        rho.index_add_(0, bi, V * K.W(rb, h))
        wall_rho, wall_count = self._wall_self()
        rho_w = wall_rho.clone().index_add_(0, bb, V * K.W(rb, h))
        gf = torch.zeros_like(x).index_add_(0, i, gw)
        gb = torch.zeros_like(x).index_add_(0, bi, gwb)
        s2 = torch.zeros(n, dtype=x.dtype, device=x.device).index_add_(0, i, (gw * gw).sum(-1))
        # diagonal of the projection: kappa_k changes rho~*_k by -dt^2 kappa_k / alpha_k
        Df = ((gf + gb) ** 2).sum(-1) + s2
        D = torch.cat([Df,
                       torch.zeros(nw, dtype=x.dtype, device=x.device).index_add_(0, bb, (gwb * gwb).sum(-1))])
        alpha = torch.where(D > 1e-9 / h ** 2, 1.0 / D.clamp_min(1e-30), torch.zeros_like(D))
        # cap the wall factor at a few times a full-lattice fluid particle's: uncapped, a wall particle
        # with few fluid neighbours over-corrects in Jacobi (a runaway dam-break front); capped at 1x,
        # Jacobi needs many more iterations per step (BENCHMARKS.md, "Hydrostatic tank", item 8)
        alpha[n:] = alpha[n:].clamp(max=WALL_ALPHA_CAP * self._alpha_lattice)
        count = torch.cat([torch.bincount(i, minlength=n) + torch.bincount(bi, minlength=n),
                           wall_count + torch.bincount(bb, minlength=nw)])
        return dict(i=i, j=j, r=r, gw=gw, bi=bi, bb=bb, gwb=gwb, rho=rho,
                    rho_all=torch.cat([rho, rho_w]), alpha=alpha, count=count, n=n)

    def _neighbourhood_native(self, x):
        """The same quantities from the native engine: CSR neighbour lists (the walls' grid built
        once), per-pair V gradW and W, densities, factors and counts in one pass."""
        from .. import native

        n, nw = x.shape[0], self.wall.shape[0]
        if self._wall_grid is None:
            self._wall_grid = build_grid(self.wall, self.h)
        rowptr, col = neighbor_lists(x, self.h)
        browptr, bcol = neighbor_lists(x, self.h, self.wall, grid=self._wall_grid)
        wall_rho, wall_count = self._wall_self()
        t = native.load().dfsph_neighbourhood(x, self.wall, rowptr, col, browptr, bcol, wall_rho.contiguous(),
                                              wall_count.contiguous(), self.V, self.h,
                                              WALL_ALPHA_CAP * self._alpha_lattice)
        return dict(native=t, rowptr=rowptr, col=col, browptr=browptr, bcol=bcol, w=t[0], rho=t[4][:n],
                    rho_all=t[4], alpha=t[5], count=t[6], n=n)

    def _div(self, v, nb):
        """Density rates of fluid and wall particles (one vector, fluid first):
        sum_j V (v_i - v_j) . gradW_ij + sum_b V v_i . gradW_ib   and   sum_i V v_i . gradW_ib."""
        i, j, bi, bb, n = nb["i"], nb["j"], nb["bi"], nb["bb"], nb["n"]
        out = torch.zeros(nb["alpha"].shape[0], dtype=v.dtype, device=v.device)
        out.index_add_(0, i, ((v[i] - v[j]) * nb["gw"]).sum(-1))
        vb = (v[bi] * nb["gwb"]).sum(-1)
        out.index_add_(0, bi, vb)
        out.index_add_(0, n + bb, vb)
        return out

    def _velocity_change(self, kappa, nb, dt):
        """dv_i = -dt [sum_j V (kappa_i + kappa_j) gradW_ij + sum_b V (kappa_i + kappa_b) gradW_ib]
        = -dt (D^T kappa)_i, kappa = (fluid, wall)."""
        i, j, bi, bb, n = nb["i"], nb["j"], nb["bi"], nb["bb"], nb["n"]
        dv = torch.zeros((n, 3), dtype=kappa.dtype, device=kappa.device)
        dv.index_add_(0, i, (kappa[i] + kappa[j])[:, None] * nb["gw"])
        dv.index_add_(0, bi, (kappa[bi] + kappa[n + bb])[:, None] * nb["gwb"])
        return -dt * dv

    def _solve(self, v, nb, dt, kappa, residual: str, scale, tol, min_iters, warm: float):
        """Jacobi iterations on the pressure-like kappa of fluid and wall particles (Bender &
        Koschier 2017, Alg. 2/3): kappa_k += max(residual_k(v* + dv(kappa)), 0) alpha_k / scale
        (``residual``: "density" or "divergence", see ``_residuals``),
        warm-started with ``warm`` x the previous step's kappa. The error is the compression summed
        over fluid and wall particles, divided by the number of fluid particles. v is updated in
        place.
        Jacobi is not guaranteed to converge: where particles are crushed together (half a
        scene mirrored into the box) the diagonal alpha misjudges the coupling and the error grew
        20-fold per iteration to NaN. An update after which the error more than doubles (or turns
        NaN) is therefore taken back and redone with half the relaxation, which stays halved for
        the rest of the solve. Returns (kappa, iterations, error, halvings)."""
        alpha = nb["alpha"]
        if kappa is None or kappa.shape != alpha.shape or warm <= 0:
            kappa = torch.zeros_like(alpha)
        else:
            kappa = torch.where(alpha > 0, warm * kappa, torch.zeros_like(kappa))
        if "native" in nb:  # the same loop in C++ (dfsph_solve in csrc/sim_cpu.cpp)
            from .. import native

            mode = {"density": 0, "divergence": 1}[residual]
            kappa, info = native.load().dfsph_solve(v, kappa, nb["rowptr"], nb["col"], nb["browptr"], nb["bcol"],
                                                    nb["native"], mode, DIVERGENCE_MIN_NEIGHBOURS, dt, scale, tol,
                                                    min_iters, self.p.max_iterations)
            return kappa, int(info[0]), float(info[1]), int(info[2])
        residual = self._residuals(residual, nb, dt)
        v0 = v.clone()
        err, it, omega, halvings = 0.0, 0, 1.0, 0
        err_prev, kappa_prev, update = math.inf, kappa, None
        for it in range(1, self.p.max_iterations + 1):
            v.copy_(v0 + self._velocity_change(kappa, nb, dt))
            res = residual(v)
            err = float(res.clamp_min(0.0).sum()) / max(nb["n"], 1)
            if update is not None and not err <= 2.0 * err_prev and halvings < 20:
                omega *= 0.5
                halvings += 1
                kappa = kappa_prev + omega * update
                continue
            if it > min_iters and err <= tol:
                break
            kappa_prev, err_prev = kappa, err
            update = res.clamp_min(0.0) * alpha / scale
            kappa = kappa + omega * update
        return kappa, it, err, halvings

    def _residuals(self, which, nb, dt):
        """The residual of v for the two solves:
        density:    rho~_k + dt * div_k(v) - 1 for fluid and wall particles;
        divergence: dt * div_k(v), 0 for particles with fewer than 20 neighbours (fluid + wall):
                    their divergence estimate is meaningless."""
        if which == "density":
            return lambda vv: nb["rho_all"] + dt * self._div(vv, nb) - 1.0
        enough = nb["count"] >= DIVERGENCE_MIN_NEIGHBOURS
        zero = torch.zeros_like(nb["alpha"])
        return lambda vv: torch.where(enough, self._div(vv, nb), zero) * dt

    def _density_solve(self, v, nb, dt):
        """Constant density: rho~_k + dt * div_k(v) -> 1 for fluid and wall particles."""
        self._kappa, it, err, halvings = self._solve(v, nb, dt, self._kappa, "density", dt * dt,
                                                     self.p.density_tol, self.p.min_iterations, self.warm)
        return it, err, halvings

    def _divergence_solve(self, v, nb, dt):
        """Divergence free: div_k(v) -> 0 (error measured as div * dt)."""
        self._kappa_v, it, err, halvings = self._solve(v, nb, dt, self._kappa_v, "divergence", dt * dt,
                                                       self.p.divergence_tol, 1, self.warm)
        return it, err, halvings

    # ---- one step -------------------------------------------------------------------------------
    def step(self, x: torch.Tensor, v: torch.Tensor, dt_max: float) -> dict:
        p = self.p
        cached = self._cache is not None and self._cache[0] is x and self._cache[1] == x._version
        nb = self._cache[2] if cached else self._neighbourhood(x)
        n = x.shape[0]
        vmax_now = float(v.norm(dim=-1).max()) if n else 0.0
        dt = min(p.cfl * self.spacing / max(vmax_now, 1e-9), self.dt_force)  # 1. CFL and force limits
        dt = even_step(min(max(dt, p.dt_min), p.dt_max), dt_max)
        # 2. non-pressure forces
        v.add_(dt * self.g)
        if p.xsph and "native" in nb:
            from .. import native

            v.copy_(native.load().csr_xsph(v, nb["rowptr"], nb["col"], nb["w"], self.V * p.xsph))
        elif p.xsph:
            v.copy_(xsph(v, nb["i"], nb["j"], nb["r"], self.V, self.h, p.xsph, self.kernel))
        visc_it = 0
        if p.viscosity and "native" in nb:
            lists = (nb["rowptr"], nb["col"], nb["browptr"], nb["bcol"])
            vv, visc_it = implicit_viscosity(v, x, None, None, None, None, self.wall, self.V, self.h,
                                             p.viscosity * dt, kernel=self.kernel, boundary=p.viscosity_boundary,
                                             lists=lists)
            v.copy_(vv)
        elif p.viscosity:
            vv, visc_it = implicit_viscosity(v, x, nb["i"], nb["j"], nb["bi"], nb["bb"], self.wall,
                                             self.V, self.h, p.viscosity * dt, kernel=self.kernel,
                                             boundary=p.viscosity_boundary)
            v.copy_(vv)
        # 3. constant density
        it_rho, err_rho, halved = self._density_solve(v, nb, dt)
        limited = limit_speed(v, self.vmax)
        # 4. advect, clamp into the box (safety net), new neighbourhood
        x.add_(dt * v)
        moved = enforce_box(x, v, self.domain, self.margin)
        nb = self._neighbourhood(x)
        # 5. divergence free
        it_div, err_div, halved_div = self._divergence_solve(v, nb, dt)
        limited += limit_speed(v, self.vmax)
        self._cache = (x, x._version, nb)
        return {"dt": dt, "iterations": it_rho, "density_residual": err_rho,
                "divergence_iterations": it_div, "divergence_residual": err_div,
                "viscosity_iterations": visc_it, "jacobi_halvings": halved + halved_div,
                "clamped_to_box": moved, "speed_limited": limited}
