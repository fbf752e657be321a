"""Divergence-free SPH (Bender & Koschier 2015; 2017 Alg. 1-3), in normalised densities
rho~ = rho / rho0 and rest volumes V = m / rho0.

One step, read top to bottom in ``step``:
  1. time step: the CFL limit dt = cfl * 2r / max|v| and the force limit
     dt = force_cfl * sqrt(2r / |g|) (Monaghan 1992), clamped to [dt_min, dt_max] and the frame end
  2. non-pressure forces: gravity, XSPH smoothing, implicit viscosity      -> v*
  3. constant-density solve (Jacobi on kappa >= 0, warm-started with half the last kappa):
        v        = v* - dt [sum_j V (kappa_i + kappa_j) gradW_ij + sum_b V (kappa_i + kappa_b) gradW_ib]
        rho~*_i  = rho~_i + dt [sum_j V (v_i - v_j) . gradW_ij + sum_b V v_i . gradW_ib]
        kappa_i += max(rho~*_i - 1, 0) alpha_i / dt^2      until mean(max(rho~* - 1, 0)) < density_tol
     alpha_i = 1 / ((g_f + 2 g_b) . (g_f + g_b) + sum_j |V gradW_ij|^2), g_f = sum_j V gradW_ij,
     g_b = sum_b V gradW_ib; wall values kappa_b are extrapolated from the fluid with the
     hydrostatic term (Adami et al. 2012), so walls push back as hard as the fluid pushes.
  4. x += dt v (box clamp as a safety net); neighbours, densities and alpha at the new positions
  5. divergence-free solve: the same iteration with residual dt * D rho~_i / Dt, until its mean
     is below divergence_tol (particles with < 20 neighbours are skipped).
Walls are lattice particles continuing the fluid lattice outside the box (``common``).
Kernel: Wendland C2 with support 4r (``kernels.WENDLAND``) for densities, gradients, XSPH and
viscosity. With the cubic spline a fluid lattice under hydrostatic pressure is unstable (its
speed grows ten-fold per 0.1 s from round-off) and rearranges into a glass; with Wendland C2 it
stays at rest (BENCHMARKS.md, "Hydrostatic tank").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..neighbors import neighbor_pairs
from . import kernels
from .common import (Domain, SolverBase, enforce_box, even_step, implicit_viscosity, lattice_volume,
                     limit_speed, xsph)


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
    max_speed: float | None = None  # safety net; default from the domain height

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
        if not (math.isfinite(self.viscosity) and self.viscosity >= 0):
            raise InputError("dfsph", f"viscosity must be >= 0, got {self.viscosity}")


class DFSPH(SolverBase):
    name = "dfsph"

    def __init__(self, params: DFSPHParams, domain: Domain, *, device="cpu", dtype=torch.float32):
        super().__init__(params, domain, lambda h, d: lattice_volume(kernels.WENDLAND.W, h, d),
                         device=device, dtype=dtype, kernel=kernels.WENDLAND)
        self.warm = 0.5  # warm start: half the previous step's kappa (as SPlisHSPlasH does)
        self.margin = 0.1 * self.spacing  # the box mirror is only a safety net: walls hold the fluid
        self._kappa = self._kappa_v = None
        self._cache = None  # neighbours/densities/alpha of the current positions

    def reset(self):
        self._kappa = self._kappa_v = None

    # ---- density and the DFSPH factor -------------------------------------------------------------
    def _neighbourhood(self, x):
        h, V, K = self.h, self.V, self.kernel
        i, j = neighbor_pairs(x, h)
        bi, bb = neighbor_pairs(x, h, self.wall) if self.wall.numel() else (i[:0], j[:0])
        d = x[i] - x[j]
        r = d.norm(dim=-1)
        gw = V * K.grad(d, r, h)                    # V gradW_ij
        db = x[bi] - self.wall[bb]
        gwb = V * K.grad(db, db.norm(dim=-1), h)    # V gradW_ib
        n = x.shape[0]
        rho = torch.full((n,), V * K.zero(h), dtype=x.dtype, device=x.device)
        rho.index_add_(0, i, V * K.W(r, h))
        rho.index_add_(0, bi, V * K.W(db.norm(dim=-1), h))
        gf = torch.zeros_like(x).index_add_(0, i, gw)
        gb = torch.zeros_like(x).index_add_(0, bi, gwb)
        s2 = torch.zeros(n, dtype=x.dtype, device=x.device).index_add_(0, i, (gw * gw).sum(-1))
        # walls carry kappa_b ~ kappa_i (extrapolated), so kappa_i changes rho~_i by
        # -dt^2 kappa_i ((g_f + 2 g_b) . (g_f + g_b) + sum_j |V gradW_ij|^2)
        D = ((gf + 2.0 * gb) * (gf + gb)).sum(-1) + s2
        D = torch.where(D > 0.5 * s2, D, s2)
        alpha = torch.where(D > 1e-9 / self.h ** 2, 1.0 / D.clamp_min(1e-30), torch.zeros_like(D))
        count = torch.bincount(i, minlength=n) + torch.bincount(bi, minlength=n)  # fluid + wall
        # wall pressure extrapolation weights (Adami et al. 2012)
        nw = self.wall.shape[0]
        wb = K.W(db.norm(dim=-1), h)
        wall_wsum = torch.zeros(nw, dtype=x.dtype, device=x.device).index_add_(0, bb, wb)
        wall_hydro = torch.zeros(nw, dtype=x.dtype, device=x.device).index_add_(0, bb, wb * ((-db) @ self.g))
        return dict(i=i, j=j, r=r, gw=gw, bi=bi, bb=bb, gwb=gwb, rho=rho, alpha=alpha, count=count,
                    wb=wb, wall_wsum=wall_wsum, wall_hydro=wall_hydro)

    def _div(self, v, nb):
        """sum_j V (v_i - v_j) . gradW_ij + sum_b V v_i . gradW_ib"""
        i, j, bi = nb["i"], nb["j"], nb["bi"]
        out = torch.zeros(v.shape[0], dtype=v.dtype, device=v.device)
        out.index_add_(0, i, ((v[i] - v[j]) * nb["gw"]).sum(-1))
        out.index_add_(0, bi, (v[bi] * nb["gwb"]).sum(-1))
        return out

    def _velocity_change(self, kappa, nb, dt, hydrostatic: bool):
        """Velocity change of the pressure-like field kappa >= 0:
            dv_i = -dt [sum_j V (kappa_i + kappa_j) gradW_ij + sum_b V (kappa_i + kappa_b) gradW_ib]
        with the wall values kappa_b extrapolated from the fluid (Adami et al. 2012):
            kappa_b = sum_i W_ib (kappa_i + g . (x_b - x_i)) / sum_i W_ib   (g term: density solve)."""
        i, j, bi, bb = nb["i"], nb["j"], nb["bi"], nb["bb"]
        dv = torch.zeros((kappa.shape[0], 3), dtype=kappa.dtype, device=kappa.device)
        dv.index_add_(0, i, (kappa[i] + kappa[j])[:, None] * nb["gw"])
        if bi.numel():
            nw = self.wall.shape[0]
            num = torch.zeros(nw, dtype=kappa.dtype, device=kappa.device).index_add_(0, bb, nb["wb"] * kappa[bi])
            if hydrostatic:
                num = num + nb["wall_hydro"]
            kb = (num / nb["wall_wsum"].clamp_min(1e-30)).clamp_min(0.0)
            dv.index_add_(0, bi, (kappa[bi] + kb[bb])[:, None] * nb["gwb"])
        return -dt * dv

    def _solve(self, v, nb, dt, kappa, residual, scale, tol, min_iters, warm: float, hydrostatic: bool):
        """Jacobi iterations on the pressure-like kappa (Bender & Koschier 2017, Alg. 2/3):
        kappa_i += max(residual_i(v* + dv(kappa)), 0) alpha_i / scale, warm-started with ``warm`` x
        the previous step's kappa. v is updated in place. Returns (kappa, iterations, residual)."""
        alpha = nb["alpha"]
        v0 = v.clone()
        if kappa is None or kappa.shape != alpha.shape or warm <= 0:
            kappa = torch.zeros_like(alpha)
        else:
            kappa = torch.where(alpha > 0, warm * kappa, torch.zeros_like(kappa))
        err, it = 0.0, 0
        for it in range(1, self.p.max_iterations + 1):
            v.copy_(v0 + self._velocity_change(kappa, nb, dt, hydrostatic))
            res = residual(v)
            err = float(res.clamp_min(0.0).mean())
            if it > min_iters and err <= tol:
                break
            kappa = kappa + res.clamp_min(0.0) * alpha / scale
        return kappa, it, err

    def _density_solve(self, v, nb, dt):
        """Constant density: rho~_i + dt * div_i(v) -> 1."""
        self._kappa, it, err = self._solve(
            v, nb, dt, self._kappa, lambda vv: nb["rho"] + dt * self._div(vv, nb) - 1.0, dt * dt,
            self.p.density_tol, self.p.min_iterations, self.warm, True)
        return it, err

    def _divergence_solve(self, v, nb, dt):
        """Divergence free: div_i(v) -> 0 (error measured as div * dt); particles with fewer than
        20 neighbours (fluid + wall) are skipped: their divergence estimate is meaningless."""
        enough = nb["count"] >= 20
        zero = torch.zeros_like(nb["rho"])
        self._kappa_v, it, err = self._solve(
            v, nb, dt, self._kappa_v, lambda vv: torch.where(enough, self._div(vv, nb), zero) * dt,
            dt * dt, self.p.divergence_tol, 1, self.warm, False)
        return it, err

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
        if p.xsph:
            v.copy_(xsph(v, nb["i"], nb["j"], nb["r"], self.V, self.h, p.xsph, self.kernel))
        visc_it = 0
        if p.viscosity:
            vv, visc_it = implicit_viscosity(v, x, nb["i"], nb["j"], nb["bi"], nb["bb"], self.wall,
                                             self.V, self.h, p.viscosity * dt, kernel=self.kernel)
            v.copy_(vv)
        # 3. constant density
        it_rho, err_rho = self._density_solve(v, nb, dt)
        limited = limit_speed(v, self.vmax)
        # 4. advect, clamp into the box (safety net), new neighbourhood
        x.add_(dt * v)
        moved = enforce_box(x, v, self.domain, self.margin)
        nb = self._neighbourhood(x)
        # 5. divergence free
        it_div, err_div = self._divergence_solve(v, nb, dt)
        limited += limit_speed(v, self.vmax)
        self._cache = (x, x._version, nb)
        return {"dt": dt, "iterations": it_rho, "density_residual": err_rho,
                "divergence_iterations": it_div, "divergence_residual": err_div,
                "viscosity_iterations": visc_it, "clamped_to_box": moved, "speed_limited": limited}
