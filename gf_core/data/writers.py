"""Writing datasets in the NeRF layout (transforms_{split}.json + PNGs), the format that
``render_data`` and the torch preview renderer produce and ``load_nerf`` reads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..camera import Camera
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
