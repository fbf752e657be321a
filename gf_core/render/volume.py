"""Images of a density grid (``GridData``): emission-absorption ray marching, evenly lit
(optionally with a light from above as well), grayscale on black (the look of ScalarFlow's
background-free footage); the rig of a smoke dataset (``gf_core.data.writers.write_smoke_dataset``
writes one).

Along each camera ray through the grid's box, with extinction sigma = ``extinction`` x density,
the image is sum_i T_i (1 - exp(-sigma_i ds)) (ambient + L_i), where T_i is the transmittance from
the camera to sample i and L_i the light reaching it from above (``light`` x the transmittance
along +z to the top of the box, so dense smoke shades what lies below it; 0 by default).
Vectorised over all pixels and samples (torch ``grid_sample``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..camera import Camera
from ..formats.hdf5 import GridData


def light_transmittance(density: torch.Tensor, cell_z: float, extinction: float) -> torch.Tensor:
    """Transmittance (nx, ny, nz) from each cell centre up to the top of the box (light from +z)."""
    above = torch.flip(torch.cumsum(torch.flip(density, [2]), 2), [2]) - 0.5 * density
    return torch.exp(-extinction * cell_z * above)


def render_density(density: np.ndarray, lo, hi, cam: Camera, *, extinction: float = 15.0, ambient: float = 1.0,
                   light: float = 0.0, step_cells: float = 0.5) -> np.ndarray:
    """The (H, W) float32 image in [0, 1] of one frame's density (nx, ny, nz) in the box [lo, hi].

    The default lighting is uniform (``ambient`` only): the image is then a function of the density
    alone, as for an evenly lit capture. With ``light`` >
    0, smoke is lit from above as well and shades what lies below it; its brightness then varies
    with the light, which images alone cannot tell apart from a change of density."""
    d = torch.as_tensor(np.asarray(density, np.float32))
    lo_t, hi_t = (torch.as_tensor(np.asarray(v, np.float64)) for v in (lo, hi))
    n = torch.tensor(d.shape, dtype=torch.float64)
    cell = (hi_t - lo_t) / n
    ds = float(cell.min()) * step_cells
    shade = ambient + light * light_transmittance(d, float(cell[2]), extinction) if light > 0 else \
        torch.full_like(d, ambient)
    # rays: one through each pixel centre
    c2w = torch.as_tensor(cam.camera_to_world, dtype=torch.float64)
    jj, ii = torch.meshgrid(torch.arange(cam.width, dtype=torch.float64) + 0.5,
                            torch.arange(cam.height, dtype=torch.float64) + 0.5, indexing="xy")
    dirs_c = torch.stack([(jj - cam.cx) / cam.fx, (ii - cam.cy) / cam.fy, torch.ones_like(jj)], -1)
    dirs = dirs_c @ c2w[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3]
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)  # rays along a face
    t0 = ((lo_t - o) * inv)
    t1 = ((hi_t - o) * inv)
    tn = torch.minimum(t0, t1).amax(-1).clamp_min(0)
    tf = torch.maximum(t0, t1).amin(-1)
    hit = tf > tn
    length = float((hi_t - lo_t).norm())
    steps = int(math.ceil(length / ds))
    ts = tn[..., None] + (torch.arange(steps, dtype=torch.float64) + 0.5) * ds          # (H, W, S)
    inside = (ts < tf[..., None]) & hit[..., None]
    pts = o + ts[..., None] * dirs[..., None, :]                                       # (H, W, S, 3)
    g = 2 * (pts - lo_t) / (hi_t - lo_t) - 1                                           # [-1, 1] over the box
    # align_corners=False: -1 and 1 are the box's faces, cell centres in between
    grid = g.flip(-1).reshape(1, cam.height, cam.width * steps, 1, 3).to(torch.float32)
    vals = F.grid_sample(torch.stack([d, d * shade])[None], grid, mode="bilinear", padding_mode="zeros",
                         align_corners=False)[0, :, :, :, 0].reshape(2, cam.height, cam.width, steps)
    sigma = extinction * vals[0].clamp_min(0).double() * inside
    alpha = 1 - torch.exp(-sigma * ds)
    trans = torch.exp(-torch.cumsum(sigma * ds, -1) + sigma * ds)                    # before each sample
    lit = torch.where(vals[0] > 1e-8, vals[1] / vals[0].clamp_min(1e-8), torch.zeros_like(vals[0])).double()
    img = (trans * alpha * lit).sum(-1)
    return img.clamp(0, 1).to(torch.float32).numpy()


def volume_rig(g: GridData, *, views: int, test_views: int, resolution: int, fov_deg: float, arc_deg: float,
               elevation_deg: float, test_elevation_deg: float | None) -> tuple[list[Camera], list[Camera]]:
    """Training cameras on a frontal arc around the grid's box; held-out camera k halfway between
    training cameras k and k + 1 (the rule of ``render_data.scene_builder.camera_rig``), so that no
    held-out view repeats a training one."""
    lo, hi = np.asarray(g.domain_min), np.asarray(g.domain_max)
    target = 0.5 * (lo + hi)
    fx = 0.5 * resolution / math.tan(math.radians(fov_deg) / 2)
    radius = 1.15 * float(np.linalg.norm(hi - lo)) / 2 / math.tan(math.radians(fov_deg) / 2)

    def at(angle_deg: float, elev_deg: float, name: str) -> Camera:
        a, e = math.radians(angle_deg), math.radians(elev_deg)
        eye = target + radius * np.array([math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), math.sin(e)])
        return Camera.look_at(eye, target, (0.0, 0.0, 1.0), fx=fx, width=resolution, height=resolution, name=name)

    angles = np.linspace(-arc_deg / 2, arc_deg / 2, views) if views > 1 else np.zeros(1)
    train = [at(float(a), elevation_deg, f"view_{k}") for k, a in enumerate(angles)]
    step = arc_deg / max(views - 1, 1)
    e = elevation_deg if test_elevation_deg is None else test_elevation_deg
    test = [at(-arc_deg / 2 + step * (k + 0.5), e, f"test_{k}") for k in range(test_views)]
    return train, test


__all__ = ["render_density", "light_transmittance", "volume_rig"]
