"""A rising smoke plume on a grid: the ground truth for smoke reconstruction (a density field per
frame), made by the project itself.

Stable fluids (Stam 1999) on a collocated grid of cell centres, z up, in a closed box: each step
injects density, heat and an upward velocity in a spherical source near the floor (its density
perturbed by seeded noise, as a real inflow is), advects velocity, density and heat
semi-Lagrangian (trilinear), adds buoyancy (heat up, density down, Boussinesq) and vorticity
confinement (Fedkiw et al. 2001: the small swirls that numerical diffusion removes), and projects
the velocity onto its divergence-free part (the pressure Poisson equation by conjugate
gradients, with the Laplacian that the discrete divergence and gradient make, so the projected
velocity is discretely divergence-free; walls with zero normal velocity). Sub-steps keep the CFL number at or below
``cfl``, so a large frame interval stays stable. Vectorised torch throughout.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from ..formats.hdf5 import GridData


@dataclass
class PlumeConfig:
    cells: int = 48                        # cells along the domain's longest side
    domain: tuple = (0.4, 0.4, 0.6)        # metres (x, y, z); the box starts at (-x/2, -y/2, 0)
    seconds: float = 2.0
    fps: float = 30.0
    source_center: tuple = (0.0, 0.0, 0.06)
    source_radius: float = 0.035           # metres
    source_speed: float = 0.5              # m/s upwards in the source
    source_noise: float = 0.8              # relative amplitude of the source density's noise
    source_wobble: float = 0.6             # m/s: a random horizontal velocity given to the whole source each step
    buoyancy: float = 3.0                  # m/s^2 per unit of heat
    weight: float = 0.2                    # m/s^2 per unit of density (downwards)
    cooling: float = 1.5                   # 1/s: heat decays as exp(-cooling t)
    vorticity: float = 5.0                 # confinement strength (dimensionless, x cell size)
    cfl: float = 1.5                       # at most this many cells per sub-step
    cg_iterations: int = 150               # pressure solve (conjugate-gradient iterations at most)
    seed: int = 0

    def check(self) -> None:
        vals = {k: v for k, v in asdict(self).items() if isinstance(v, (int, float))}
        for k, v in vals.items():
            if not math.isfinite(v):
                raise InputError(f"smoke_plume.{k}", f"must be finite, got {v}")
        if self.cells < 8:
            raise InputError("smoke_plume.cells", f"must be >= 8, got {self.cells}")
        for k in ("seconds", "fps", "source_radius", "cfl"):
            if not getattr(self, k) > 0:
                raise InputError(f"smoke_plume.{k}", f"must be > 0, got {getattr(self, k)}")
        if len(self.domain) != 3 or min(self.domain) <= 0:
            raise InputError("smoke_plume.domain", f"must be 3 positive lengths, got {self.domain}")


def _sample(field: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """Trilinear values of ``field`` (C, nx, ny, nz) at cell-index positions ``pos`` (3, nx, ny, nz),
    clamped to the grid."""
    n = torch.tensor(field.shape[1:], dtype=pos.dtype, device=pos.device).view(3, 1, 1, 1)
    g = 2 * pos / (n - 1) - 1                                  # align_corners: -1, 1 = first, last centre
    # grid_sample's 5D input is (N, C, D, H, W) with grid (..., [W, H, D]); our axes (x, y, z) are (D, H, W)
    grid = g.permute(1, 2, 3, 0).flip(-1)[None]                # (1, nx, ny, nz, [z, y, x])
    out = F.grid_sample(field[None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0]


def _grad(p: torch.Tensor, h: float) -> torch.Tensor:
    """Central-difference gradient of (nx, ny, nz) with one-sided copies at the walls: (3, nx, ny, nz)."""
    q = F.pad(p[None, None], (1, 1, 1, 1, 1, 1), mode="replicate")[0, 0]
    return torch.stack([(q[2:, 1:-1, 1:-1] - q[:-2, 1:-1, 1:-1]), (q[1:-1, 2:, 1:-1] - q[1:-1, :-2, 1:-1]),
                        (q[1:-1, 1:-1, 2:] - q[1:-1, 1:-1, :-2])]) / (2 * h)


def _div(v: torch.Tensor, h: float) -> torch.Tensor:
    """Central-difference divergence of (3, nx, ny, nz); the walls' normal velocity is zero."""
    q = F.pad(v[None], (1, 1, 1, 1, 1, 1))[0]
    return ((q[0, 2:, 1:-1, 1:-1] - q[0, :-2, 1:-1, 1:-1]) + (q[1, 1:-1, 2:, 1:-1] - q[1, 1:-1, :-2, 1:-1])
            + (q[2, 1:-1, 1:-1, 2:] - q[2, 1:-1, 1:-1, :-2])) / (2 * h)


def _div_t(p: torch.Tensor, h: float) -> torch.Tensor:
    """The transpose of ``_div``: (3, nx, ny, nz) from (nx, ny, nz), p taken as 0 beyond the walls."""
    q = F.pad(p[None, None], (1, 1, 1, 1, 1, 1))[0, 0]
    return torch.stack([(q[:-2, 1:-1, 1:-1] - q[2:, 1:-1, 1:-1]), (q[1:-1, :-2, 1:-1] - q[1:-1, 2:, 1:-1]),
                        (q[1:-1, 1:-1, :-2] - q[1:-1, 1:-1, 2:])]) / (2 * h)


def _project(v: torch.Tensor, h: float, iterations: int) -> torch.Tensor:
    """The divergence-free part of ``v`` (closed walls): w = W (v + D^T p) with D the divergence
    and W the walls' zero normal velocity, p solving (D W D^T) p = -D W v by conjugate gradients.
    D W D^T is the Laplacian that this divergence and gradient make (symmetric, positive
    semi-definite), so D w = 0 up to the solver's tolerance."""
    v = _walls(v)
    b = -_div(v, h)
    x = torch.zeros_like(b)
    r = b.clone()
    d = r.clone()
    rr = (r * r).sum()
    tol = 1e-12 * float(rr) + 1e-30
    for _ in range(iterations):
        Ad = _div(_walls(_div_t(d, h)), h)
        alpha = rr / (d * Ad).sum().clamp_min(1e-30)
        x = x + alpha * d
        r = r - alpha * Ad
        rr_new = (r * r).sum()
        if float(rr_new) < tol:
            break
        d = r + (rr_new / rr) * d
        rr = rr_new
    return _walls(v + _div_t(x, h))


def _walls(v: torch.Tensor) -> torch.Tensor:
    """No flow through the box's faces: the normal component is zero in the outermost cells."""
    v = v.clone()
    v[0, 0] = v[0, -1] = 0
    v[1, :, 0] = v[1, :, -1] = 0
    v[2, :, :, 0] = v[2, :, :, -1] = 0
    return v


def simulate_plume(cfg: PlumeConfig | None = None, *, progress=None) -> GridData:
    """The plume's density at every frame (``GridData``); ``progress(frame, frames)`` after each."""
    cfg = cfg or PlumeConfig()
    cfg.check()
    dom = np.asarray(cfg.domain, np.float64)
    h = float(dom.max() / cfg.cells)
    n = tuple(int(max(4, round(d / h))) for d in dom)
    lo = np.array([-dom[0] / 2, -dom[1] / 2, 0.0])
    hi = lo + np.asarray(n) * h
    dt_frame = 1.0 / cfg.fps
    frames = int(round(cfg.seconds * cfg.fps)) + 1
    gen = torch.Generator().manual_seed(int(cfg.seed))
    dtype = torch.float32
    centres = [torch.as_tensor(lo[a] + (np.arange(n[a]) + 0.5) * h, dtype=dtype) for a in range(3)]
    X, Y, Z = torch.meshgrid(*centres, indexing="ij")
    c = np.asarray(cfg.source_center, np.float64)
    r2 = ((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / cfg.source_radius ** 2
    source = torch.clamp(1.5 - r2, 0, 1)                      # soft-edged sphere
    idx = torch.stack(torch.meshgrid(*[torch.arange(k, dtype=dtype) for k in n], indexing="ij"))
    vel = torch.zeros((3,) + n, dtype=dtype)
    dens = torch.zeros(n, dtype=dtype)
    heat = torch.zeros(n, dtype=dtype)
    out = np.zeros((frames,) + n, np.float32)
    t = 0.0
    for f in range(frames):
        if f > 0:
            t_end = f * dt_frame
            while t < t_end - 1e-12:
                vmax = float(vel.abs().max()) + cfg.source_speed
                dt = min(t_end - t, cfg.cfl * h / max(vmax, 1e-6))
                vel, dens, heat = _step(vel, dens, heat, source, idx, h, dt, cfg, gen)
                t += dt
        if not (torch.isfinite(dens).all() and torch.isfinite(vel).all()):
            raise FloatingPointError(f"smoke plume: non-finite field at frame {f} (t = {t:.3f} s)")
        out[f] = dens.numpy()
        if progress is not None:
            progress(f + 1, frames)
    return GridData(density=out, times=np.arange(frames) * dt_frame, domain_min=tuple(lo), domain_max=tuple(hi),
                    fps=cfg.fps, scene="smoke_plume", config={"solver": "stable_fluids", **asdict(cfg)})


def _step(vel, dens, heat, source, idx, h, dt, cfg: PlumeConfig, gen):
    # sources: density (noisy), heat and an upward push inside the source sphere
    noise = 1 + cfg.source_noise * (2 * torch.rand(source.shape, generator=gen) - 1)
    dens = torch.maximum(dens, source * noise.clamp_min(0))
    heat = torch.maximum(heat, source)
    vel = vel.clone()
    vel[2] = torch.where(source > 0, torch.maximum(vel[2], source * cfg.source_speed), vel[2])
    if cfg.source_wobble > 0:  # an unsteady inflow: the source pushes sideways, a new direction each step
        side = cfg.source_wobble * (2 * torch.rand(2, generator=gen) - 1)
        vel[:2] = vel[:2] + source * side.view(2, 1, 1, 1)
    # semi-Lagrangian advection: values carried from where the flow comes from
    back = idx - dt * vel / h
    adv = _sample(torch.cat([vel, dens[None], heat[None]]), back)
    vel, dens, heat = adv[:3], adv[3].clamp_min(0), adv[4].clamp_min(0)
    # buoyancy (Boussinesq) and cooling
    vel[2] = vel[2] + dt * (cfg.buoyancy * heat - cfg.weight * dens)
    heat = heat * math.exp(-cfg.cooling * dt)
    # vorticity confinement: f = eps h (N x omega), N the unit gradient of |omega|
    if cfg.vorticity > 0:
        gx, gy, gz = (_grad(vel[a], h) for a in range(3))
        omega = torch.stack([gz[1] - gy[2], gx[2] - gz[0], gy[0] - gx[1]])
        mag = omega.norm(dim=0)
        nrm = _grad(mag, h)
        nrm = nrm / nrm.norm(dim=0).clamp_min(1e-9)
        vel = vel + dt * cfg.vorticity * h * torch.linalg.cross(nrm, omega, dim=0)
    # projection onto the divergence-free velocities (the pressure absorbs dt)
    return _project(vel, h, cfg.cg_iterations), dens, heat


__all__ = ["PlumeConfig", "simulate_plume"]
