"""Writing datasets in the NeRF layout (transforms_{split}.json + PNGs), the format that
``render_data``, the torch preview renderer and the smoke plume's ray marcher produce and
``load_nerf`` reads."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError
from ..formats.hdf5 import atomic_write_text
from .images import write_png


def frame_entry(file_path: str, cam: Camera, time: float, view_id: int) -> dict:
    return {"file_path": file_path, "transform_matrix": cam.to_blender_c2w().tolist(),
            "time": float(time), "view_id": int(view_id), "fl_x": cam.fx, "fl_y": cam.fy,
            "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height}


def write_transforms(root: Path, split: str, entries: list[dict], *, fps: float | None = None,
                     extra: dict | None = None) -> Path:
    meta = dict(extra or {})
    if fps:
        meta["fps"] = float(fps)
    meta["frames"] = entries
    path = Path(root) / f"transforms_{split}.json"
    atomic_write_text(path, json.dumps(meta, indent=1))
    return path


def write_nerf_dataset(root, split: str, images, cameras, times, view_ids, *, fps=None,
                       extra: dict | None = None) -> Path:
    """Write images ((H, W, C) float in [0,1] or uint8, C in 1/3/4) with their cameras."""
    root = Path(root)
    entries = []
    for k, (img, cam, t, v) in enumerate(zip(images, cameras, times, view_ids)):
        rel = f"{split}/v{int(v):02d}_{k:05d}.png"
        write_png(root / rel, np.asarray(img))
        entries.append(frame_entry(rel, cam, t, v))
    return write_transforms(root, split, entries, fps=fps, extra=extra)


def write_smoke_dataset(grid_path: Path, out: Path, *, views: int = 5, test_views: int = 1, resolution: int = 128,
                         fov_deg: float = 40.0, arc_deg: float = 90.0, elevation_deg: float = 15.0,
                         test_elevation_deg: float | None = None, frames: slice = slice(None),
                         extinction: float = 15.0, ambient: float = 1.0, light: float = 0.0, log=print) -> Path:
    """Render ``grid_path`` (a grid.h5) into a NeRF-layout dataset in ``out``: grayscale PNGs,
    transforms_{train,test}.json with the grid's box as ``scene_box`` and ``gt_density`` naming a
    copy of the grid (what ``gf-cli evaluate`` compares a smoke reconstruction with)."""
    from ..formats.hdf5 import read_grid
    from ..render.volume import render_density, volume_rig

    g = read_grid(grid_path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    train, test = volume_rig(g, views=views, test_views=test_views, resolution=resolution, fov_deg=fov_deg,
                             arc_deg=arc_deg, elevation_deg=elevation_deg, test_elevation_deg=test_elevation_deg)
    keep = list(range(g.density.shape[0]))[frames]
    if not keep:
        raise InputError("--frames", f"selects none of the grid's {g.density.shape[0]} frames ({grid_path})")
    entries = {"train": [], "test": []}
    for k, f in enumerate(keep):
        for split, cams, v0 in (("train", train, 0), ("test", test, len(train))):
            for v, cam in enumerate(cams):
                rel = f"{split}/v{v:02d}_f{f:05d}.png"
                img = render_density(g.density[f], g.domain_min, g.domain_max, cam, extinction=extinction,
                                     ambient=ambient, light=light)
                write_png(out / rel, img[..., None])
                entries[split].append(frame_entry(rel, cam, float(g.times[f]), v0 + v))
        log(f"frame {k + 1}/{len(keep)} (t = {g.times[f]:.3f} s): {len(train) + len(test)} images")
    gt = out / "gt_density.h5"
    if Path(grid_path).resolve() != gt.resolve():
        shutil.copyfile(grid_path, gt)
    extra = {"scene_box": [list(map(float, g.domain_min)), list(map(float, g.domain_max))],
             "background": [0.0, 0.0, 0.0], "gt_density": gt.name, "time_unit": "seconds",
             "volume_render": {"extinction": extinction, "ambient": ambient, "light_from_above": light}}
    for split, e in entries.items():
        if e:
            write_transforms(out, split, e, fps=g.fps, extra=extra)
    return out
