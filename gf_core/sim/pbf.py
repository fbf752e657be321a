"""Position Based Fluids (Macklin & Mueller 2013), in normalised densities rho~ = V sum_j W_ij.

One substep, read top to bottom in ``step``:
  0. dt = min(dt, cfl 2r / max|v|, force_cfl sqrt(2r / |g|)), dividing the time to the next
     frame evenly
  1. v += dt g ;  x* = x + dt v                         (predict)
  2. neighbours of x* (fluid and wall particles)
  3. ``iterations`` times (their Algorithm 1):
        C_i      = max(rho~_i - 1, 0)                    (unilateral density constraint)
        lambda_i = -C_i / (|sum_j V gradW_ij + sum_b V gradW_ib|^2 + sum_j |V gradW_ij|^2 + eps)
        s_corr   = -k (W(r_ij) / W(dq h))^n / G         (tensile instability, k=0.1, n=4, dq=0.2;
                                                          G = sum |grad C|^2 of a lattice particle
                                                          gives it the units of lambda)
        dx_i     = sum_j V (lambda_i + lambda_j + s_corr) gradW_ij + sum_b V lambda_i gradW_ib
        x* += dx ; clamp into the box
  4. v = (x* - x) / dt ; vorticity confinement (optional) ; XSPH ; implicit viscosity
  5. x = x*
W is poly6 for densities (paper Eq. 6), the spiky gradient for constraint gradients.
``PBF.from_positions`` accepts any particle set (e.g. a reconstruction) and estimates its
spacing and rest density from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import InputError
from ..sph.neighbors import build_grid, csr_rows, neighbor_lists, neighbor_pairs
from ..sph import kernels
from .common import (VISCOSITY_BOUNDARIES, Domain, SolverBase, enforce_box, estimate_rest_state, even_step,
                     implicit_viscosity, lattice_volume, limit_speed, pick_backend, xsph)


@dataclass
class PBFParams:
    particle_radius: float
    rest_density: float = 1000.0
    gravity: tuple = (0.0, 0.0, -9.81)
    dt: float = 1.0 / 240.0        # substep (upper bound)
    cfl: float = 1.0               # ... also limited to cfl * 2r / max|v|
    force_cfl: float = 0.15        # ... and to force_cfl * sqrt(2r / |g|) (a fluid at rest)
    iterations: int = 4
    relaxation: float = 0.01       # eps, relative to sum |grad C|^2 of a lattice particle
    scorr_k: float = 0.1
    scorr_n: int = 4
    scorr_dq: float = 0.2
    xsph: float = 0.01
    vorticity: float = 0.0         # vorticity confinement strength (0: off)
    viscosity: float = 0.0         # kinematic viscosity nu [m^2/s], solved implicitly
    viscosity_boundary: str = "free-slip"  # or "no-slip": the walls' friction (common.implicit_viscosity)
    backend: str = "auto"          # constraint iterations: "native" (C++, CPU), "torch" (reference), "auto"
    rest_volume: float | None = None  # V = 1 / n0; None: from a lattice of spacing 2 r
    max_speed: float | None = None

    def validate(self):
        for k in ("particle_radius", "rest_density", "dt", "relaxation", "cfl", "force_cfl"):
            val = getattr(self, k)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise InputError("pbf", f"{k} must be a positive number, got {val!r}")
        if int(self.iterations) < 1:
            raise InputError("pbf", f"iterations must be >= 1, got {self.iterations}")
        if not 0 <= self.xsph <= 1:
            raise InputError("pbf", f"xsph must be in [0, 1], got {self.xsph}")
        for k in ("vorticity", "viscosity", "scorr_k"):
            if not (math.isfinite(getattr(self, k)) and getattr(self, k) >= 0):
                raise InputError("pbf", f"{k} must be >= 0, got {getattr(self, k)}")
        if self.backend not in ("auto", "native", "torch"):
            raise InputError("pbf", f"unknown backend {self.backend!r} (auto, native, torch)")
        if self.viscosity_boundary not in VISCOSITY_BOUNDARIES:
            raise InputError("pbf", f"unknown viscosity_boundary {self.viscosity_boundary!r} "
                                    f"({', '.join(VISCOSITY_BOUNDARIES)})")


class PBF(SolverBase):
    name = "pbf"

    def __init__(self, params: PBFParams, domain: Domain, *, device="cpu", dtype=torch.float32):
        r = params.particle_radius
        lattice_V = lattice_volume(kernels.poly6, 4.0 * r, 2.0 * r) if r > 0 and math.isfinite(r) else 1.0
        super().__init__(params, domain, lambda h, d: params.rest_volume or lattice_V,
                         device=device, dtype=dtype,
                         measure_scale=(params.rest_volume or lattice_V) / lattice_V)
        # relaxation eps in units of sum |grad C|^2 of a lattice particle
        n = int(math.ceil(self.h / self.spacing)) + 1
        grid = torch.arange(-n, n + 1, dtype=torch.float64) * self.spacing
        P = torch.stack(torch.meshgrid(grid, grid, grid, indexing="ij"), -1).reshape(-1, 3)
        rr = P.norm(dim=-1)
        gl = self.V * kernels.spiky_grad(P, rr, self.h)
        self.grad2_lattice = float((gl * gl).sum())
        self.eps = params.relaxation * self.grad2_lattice
        self.w_dq = float(kernels.poly6(torch.tensor(params.scorr_dq * self.h), self.h))
        self.native = pick_backend("pbf", params.backend, device)
        self._wall_grid = None

    @classmethod
    def from_positions(cls, positions, domain: Domain, *, rest_density: float = 1000.0, device="cpu",
                       dtype=torch.float32, **overrides) -> "PBF":
        """A PBF solver for an arbitrary particle set (``common.estimate_rest_state``)."""
        spacing, V = estimate_rest_state(positions, kernels.poly6, "pbf")
        params = PBFParams(particle_radius=spacing / 2.0, rest_density=rest_density, rest_volume=V,
                           **overrides)
        return cls(params, domain, device=device, dtype=dtype)

    def _density_terms(self, x, i, j, bi, bb):
        h, V = self.h, self.V
        d = x[i] - x[j]
        r = d.norm(dim=-1)
        db = x[bi] - self.wall[bb]
        rb = db.norm(dim=-1)
        n = x.shape[0]
        rho = torch.full((n,), V * float(kernels.poly6(torch.tensor(0.0), h)), dtype=x.dtype, device=x.device)
        rho.index_add_(0, i, V * kernels.poly6(r, h))
        rho.index_add_(0, bi, V * kernels.poly6(rb, h))
        gw = V * kernels.spiky_grad(d, r, h)
        gwb = V * kernels.spiky_grad(db, rb, h)
        return r, rho, gw, gwb

    def step(self, x: torch.Tensor, v: torch.Tensor, dt_max: float) -> dict:
        p = self.p
        vnow = float(v.norm(dim=-1).max()) if v.shape[0] else 0.0
        dt = even_step(min(p.dt, p.cfl * self.spacing / max(vnow, 1e-9), self.dt_force), dt_max)
        x0 = x.clone()
        v.add_(dt * self.g)
        limited = limit_speed(v, self.vmax)
        x.add_(dt * v)
        enforce_box(x, v, self.domain, 0.1 * self.spacing)
        constraints = self._constraints_native if self.native else self._constraints
        C, moved, (i, j, bi, bb), lists = constraints(x, v)
        v.copy_((x - x0) / dt)
        if p.vorticity:
            self._vorticity(x, v, i, j, dt)
        if p.xsph:
            r = (x[i] - x[j]).norm(dim=-1)
            v.copy_(xsph(v, i, j, r, self.V, self.h, p.xsph))
        visc_it = 0
        if p.viscosity:
            vv, visc_it = implicit_viscosity(v, x, i, j, bi, bb, self.wall, self.V, self.h, p.viscosity * dt,
                                             boundary=p.viscosity_boundary, lists=lists)
            v.copy_(vv)
        limited += limit_speed(v, self.vmax)
        err = float(C.mean()) if C is not None and C.numel() else 0.0
        return {"dt": dt, "iterations": int(p.iterations), "density_residual": err,
                "viscosity_iterations": visc_it, "clamped_to_box": moved, "speed_limited": limited}

    def _constraints(self, x, v):
        """Step 3 on the torch path (the reference): pair lists of x*, then ``iterations`` rounds of
        lambda and dx as tensor ops. Returns (C, particles clamped, pair lists, None: no CSR lists)."""
        p = self.p
        i, j = neighbor_pairs(x, self.h)
        bi, bb = neighbor_pairs(x, self.h, self.wall) if self.wall.numel() else (i[:0], j[:0])
        C, moved = None, 0
        for _ in range(int(p.iterations)):
            r, rho, gw, gwb = self._density_terms(x, i, j, bi, bb)
            C = (rho - 1.0).clamp_min(0.0)
            gsum = torch.zeros_like(x).index_add_(0, i, gw).index_add_(0, bi, gwb)
            s2 = torch.zeros_like(rho).index_add_(0, i, (gw * gw).sum(-1))
            lam = -C / ((gsum * gsum).sum(-1) + s2 + self.eps)
            # s_corr is dimensionless in the paper; here it acts as the lambda of a constraint
            # violated by k (W/W(dq))^n on a lattice particle, so it scales with the spacing
            scorr = (-p.scorr_k * (kernels.poly6(r, self.h) / self.w_dq) ** p.scorr_n / self.grad2_lattice
                     if p.scorr_k else 0.0)
            dx = torch.zeros_like(x)
            dx.index_add_(0, i, (lam[i] + lam[j] + scorr)[:, None] * gw)
            dx.index_add_(0, bi, lam[bi][:, None] * gwb)
            x.add_(dx)
            moved = enforce_box(x, v, self.domain, 0.1 * self.spacing)
        return C, moved, (i, j, bi, bb), None

    def _constraints_native(self, x, v):
        """The same iterations, each one native call over CSR lists (``csrc/sim_cpu.cpp``; the
        walls' grid built once)."""
        from .. import native

        p, ext = self.p, native.load()
        if self._wall_grid is None:
            self._wall_grid = build_grid(self.wall, self.h)
        rowptr, col = neighbor_lists(x, self.h)
        browptr, bcol = neighbor_lists(x, self.h, self.wall, grid=self._wall_grid)
        C, moved = None, 0
        for _ in range(int(p.iterations)):
            dx, C = ext.pbf_iteration(x, self.wall, rowptr, col, browptr, bcol, self.V, self.h, self.eps,
                                      float(p.scorr_k), float(p.scorr_n), self.w_dq, self.grad2_lattice)
            x.add_(dx)
            moved = enforce_box(x, v, self.domain, 0.1 * self.spacing)
        return C, moved, (csr_rows(rowptr), col, csr_rows(browptr), bcol), (rowptr, col, browptr, bcol)

    def _vorticity(self, x, v, i, j, dt):
        """Vorticity confinement (Fedkiw et al. 2001 as used by PBF): f = eps (N x omega)."""
        d = x[i] - x[j]
        r = d.norm(dim=-1)
        g = self.V * kernels.spiky_grad(d, r, self.h)
        omega = torch.zeros_like(v).index_add_(0, i, torch.cross(g, v[j] - v[i], dim=-1))  # curl v
        wn = omega.norm(dim=-1)
        eta = torch.zeros_like(v).index_add_(0, i, (wn[j] - wn[i])[:, None] * g)      # grad |omega|
        N = eta / eta.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        v.add_(dt * self.p.vorticity * torch.cross(N, omega, dim=-1))
