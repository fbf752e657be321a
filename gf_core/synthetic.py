"""Small datasets rendered by the toolkit's own splatting renderer from known moving particles:
for tests and quick checks of the reconstruction, where Blender would take minutes.

``splat_dataset`` writes the NeRF layout (RGBA PNGs, transforms_{train,test}.json with a
``scene_box``) and ``gt_sim.h5`` with the particles, exactly what ``gf-cli render-dataset`` writes.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .camera import frontal_arc
from .data.writers import frame_entry, write_transforms
from .data.images import write_png
from .formats.hdf5 import SimData, write_sim
from .render import render_points


def falling_blob(n_side: int = 9, frames: int = 8, fps: float = 10.0, *, spacing: float = 0.05,
                 seed: int = 0) -> SimData:
    """A ball of lattice particles that falls and spreads (each particle ballistic, with an outward
    velocity proportional to its offset): smooth, known motion with a filled interior."""
    rng = np.random.default_rng(seed)
    g = (np.arange(n_side) - (n_side - 1) / 2) * spacing
    P = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    P = P[np.linalg.norm(P, axis=1) <= (n_side - 1) / 2 * spacing + 1e-9]
    P = P + rng.normal(scale=0.02 * spacing, size=P.shape)
    centre = np.array([0.0, 0.0, 0.45])
    v = 0.6 * P / max(np.linalg.norm(P, axis=1).max(), 1e-9) * spacing * fps * 0.1 + np.array([0.15, 0.0, 0.0])
    gvec = np.array([0.0, 0.0, -1.0])
    times = np.arange(frames) / fps
    pos = np.stack([centre + P + v * t + 0.5 * gvec * t * t for t in times]).astype(np.float32)
    vel = np.stack([v + gvec * t for t in times]).astype(np.float32)
    return SimData(positions=pos, velocities=vel, fps=fps, particle_radius=spacing / 2, scene="falling_blob",
                   domain_min=(-0.4, -0.4, 0.0), domain_max=(0.4, 0.4, 0.8), solver="ballistic",
                   gravity=tuple(gvec.tolist()))


def splat_dataset(root, sim: SimData, *, views: int = 5, test_views: int = 1, resolution: int = 64,
                  fov_deg: float = 40.0, distance: float = 1.6, color=(0.35, 0.6, 0.95), opacity: float = 0.8,
                  radius_factor: float = 0.6, frame_colors=None) -> Path:
    """Render ``sim`` with the Gaussian renderer into ``root`` (NeRF layout, RGBA) and copy it to
    ``root/gt_sim.h5``. Cameras: a 90-degree frontal arc (training) and views between them (held out).
    ``frame_colors`` (frames, 3), if given, is the particles' colour at each frame instead of ``color``."""
    root = Path(root)
    fx = 0.5 * resolution / math.tan(math.radians(fov_deg) / 2)
    lo, hi = np.asarray(sim.domain_min), np.asarray(sim.domain_max)
    target = 0.5 * (lo + hi)
    train = frontal_arc(views, radius=distance, target=target, height=0.3, fx=fx, width=resolution,
                        height_px=resolution)
    test = []
    if test_views:
        arc = 90.0 * (1 - 1 / max(views, 2))
        test = frontal_arc(test_views + 2, radius=distance, target=target, height=0.25, fx=fx,
                           width=resolution, height_px=resolution, arc_degrees=arc)[1:-1]
    for split, cams, v0 in (("train", train, 0), ("test", test, views)):
        if not cams:
            continue
        entries = []
        for f in range(sim.num_frames):
            look = dict(radius=radius_factor * sim.particle_radius, opacity=opacity,
                        color=color if frame_colors is None else tuple(frame_colors[f]))
            for k, cam in enumerate(cams):
                with torch.no_grad():
                    o = render_points(sim.positions[f], cam, background=torch.zeros(3), **look)
                # straight (un-premultiplied) colour with alpha, as Blender writes RGBA
                a = o.alpha.clamp(0, 1)
                rgb = torch.where(a[..., None] > 1e-6, o.color / a[..., None].clamp_min(1e-6), torch.zeros_like(o.color))
                img = torch.cat([rgb.clamp(0, 1), a[..., None]], -1).numpy()
                rel = f"{split}/v{v0 + k:02d}_f{f:05d}.png"
                write_png(root / rel, img)
                entries.append(frame_entry(rel, cam, float(sim.times[f]), v0 + k))
        write_transforms(root, split, entries, fps=sim.fps,
                         extra={"scene_box": [list(map(float, lo)), list(map(float, hi))],
                                "background": [0.0, 0.0, 0.0], "gt_particles": "gt_sim.h5",
                                "time_unit": "seconds"})
    write_sim(root / "gt_sim.h5", sim)
    return root


__all__ = ["falling_blob", "splat_dataset"]
