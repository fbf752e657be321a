"""The PINF / HyFluid video layout (ScalarFlow captures as PINF, HyFluid and their successors ship
them): ``info.json`` beside one video per camera.

info.json:
  train_videos / test_videos: [{file_name, frame_rate, frame_num, camera_angle_x,
      camera_hw: [H, W] (the video's height first: the ScalarFlow videos are portrait),
      transform_matrix: 4x4 camera-to-world, OpenGL axes (NeRF's),
      transform_matrix_list (optional): one such matrix per frame, for a moving camera}]
  frame_bkg_color: [r, g, b] in [0, 1]   the background (black after background removal)
  voxel_matrix: 4x4, voxel_scale: [sx, sy, sz] (or one number)   the fluid's box: the points
      voxel_matrix' @ (u * scale) for u in [0, 1]^3, where voxel_matrix' is voxel_matrix with its
      first and third columns swapped, as HyFluid's loader reads it
  rot: "Y" or "Z"   the world's up axis ("Y" for ScalarFlow)
  near, far, render_center, phi: the authors' orbit for novel views (not used)

``test_videos`` are the held-out cameras (split "test"); ``train_videos`` the training ones.
Frame k of a video has time k / frame_rate (seconds). The toolkit's world is z-up (gravity -z):
a y-up capture (``rot`` "Y") is turned +90 degrees about x at load (y -> z, z -> -y), cameras and
box alike; ``meta["world_from_file"]`` holds that 4x4 so results can be mapped back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError, short_repr
from .dataset import FluidDataset, FrameRecord
from .fields import matrix_value, number, path_value, read_json
from .videos import video_info

INFO = "info.json"
SPLITS = {"train": "train_videos", "test": "test_videos"}

# a y-up world turned z-up: +90 degrees about x
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def detect(path: Path, split: str) -> bool:
    """An ``info.json`` with this split's video list (the PINF / HyFluid layout)."""
    p = Path(path) / INFO
    if not p.is_file():
        return False
    try:
        meta = read_json(p)
    except InputError:
        return split == "train"  # a broken info.json is this layout's to report
    return isinstance(meta.get(SPLITS.get(split, "")), list)


def _up_turn(meta: dict, json_path: Path) -> np.ndarray:
    rot = meta.get("rot", "Z")
    if rot not in ("Y", "Z"):
        raise InputError(json_path, f"'rot' (the world's up axis) must be \"Y\" or \"Z\", got {short_repr(rot)}")
    return Y_UP_TO_Z_UP if rot == "Y" else np.eye(4)


def scene_box(meta: dict, json_path: Path, turn: np.ndarray) -> list | None:
    """The axis-aligned box (z-up world) around the ``voxel_matrix`` / ``voxel_scale`` volume."""
    if "voxel_matrix" not in meta and "voxel_scale" not in meta:
        return None
    if "voxel_matrix" not in meta or "voxel_scale" not in meta:
        raise InputError(json_path, "'voxel_matrix' and 'voxel_scale' come together (the fluid's box); one is missing")
    m = matrix_value(meta["voxel_matrix"], json_path, "top level", "voxel_matrix", shapes=((4, 4),))
    m = m[:, [2, 1, 0, 3]]
    try:
        s = np.broadcast_to(np.asarray(meta["voxel_scale"], np.float64), (3,))
    except (TypeError, ValueError):
        s = None
    if s is None or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError(json_path, f"'voxel_scale' must be one or three positive numbers, got {short_repr(meta['voxel_scale'])}")
    u = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64) * s
    corners = np.c_[u, np.ones(8)] @ (turn @ m).T
    lo, hi = corners[:, :3].min(0), corners[:, :3].max(0)
    if np.any(hi - lo <= 0):
        raise InputError(json_path, "'voxel_matrix' is singular: the fluid's box has no volume")
    return [lo.tolist(), hi.tolist()]


def _background(meta: dict, json_path: Path, channels: int) -> tuple:
    bg = meta.get("frame_bkg_color", [0.0, 0.0, 0.0])
    vals = [bg] * 3 if isinstance(bg, (int, float)) and not isinstance(bg, bool) else bg
    if not isinstance(vals, list) or len(vals) != 3 or \
            any(isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 <= x <= 1 for x in vals):
        raise InputError(json_path, f"'frame_bkg_color' must be 3 numbers in [0, 1], got {short_repr(bg)}")
    if channels == 1:
        return (float(np.dot(vals, [0.299, 0.587, 0.114])),)
    return tuple(float(x) for x in vals)


def _records(root: Path, entry, k: int, key: str, json_path: Path, turn: np.ndarray, view: int) -> list[FrameRecord]:
    where = f"{key}[{k}]"
    if not isinstance(entry, dict):
        raise InputError(json_path, f"{where}: must be an object with 'file_name', 'frame_rate', ..., got {short_repr(entry)}")
    name = path_value(entry, "file_name", json_path, where)
    if name is None:
        raise InputError(json_path, f"{where}: missing 'file_name' (the camera's video)")
    video = root / name
    n_file, w, h, _ = video_info(video)
    rate = number(entry, "frame_rate", json_path, where)
    if rate is None or rate <= 0:
        raise InputError(json_path, f"{where}: 'frame_rate' must be a positive number of frames per second, "
                                    f"got {short_repr(entry.get('frame_rate'))}")
    n = number(entry, "frame_num", json_path, where)
    if n is not None and (n < 1 or n != int(n)):
        raise InputError(json_path, f"{where}: 'frame_num' must be a positive whole number, got {short_repr(entry['frame_num'])}")
    n = n_file if n is None else int(n)
    if n > n_file:
        raise InputError(video, f"has {n_file} frames but {json_path.name} says 'frame_num' {n}")
    hw = entry.get("camera_hw")
    if hw is not None:
        if not (isinstance(hw, list) and len(hw) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in hw)):
            raise InputError(json_path, f"{where}: 'camera_hw' must be [height, width] in pixels, got {short_repr(hw)}")
        if (hw[0], hw[1]) != (h, w):
            raise InputError(video, f"video is {w}x{h} (width x height) but {json_path.name} says camera_hw "
                                    f"[{hw[0]}, {hw[1]}] (height, width)")
    angle = number(entry, "camera_angle_x", json_path, where)
    if angle is None or not 0 < angle < np.pi:
        raise InputError(json_path, f"{where}: 'camera_angle_x' must be the horizontal field of view in (0, pi) "
                                    f"radians, got {short_repr(entry.get('camera_angle_x'))}")
    if "transform_matrix_list" in entry:
        poses = entry["transform_matrix_list"]
        if not isinstance(poses, list) or len(poses) < n:
            raise InputError(json_path, f"{where}: 'transform_matrix_list' must hold one 4x4 matrix per frame ({n})")
        keys = [f"transform_matrix_list[{i}]" for i in range(n)]
    elif "transform_matrix" in entry:
        poses, keys = [entry["transform_matrix"]] * n, ["transform_matrix"] * n
    else:
        raise InputError(json_path, f"{where}: missing 'transform_matrix' (OpenGL camera-to-world)")
    cams: dict[int, Camera] = {}
    records = []
    for i in range(n):
        c = id(poses[i])
        if c not in cams:
            c2w = turn @ matrix_value(poses[i], json_path, where, keys[i], shapes=((4, 4),))
            try:
                cams[c] = Camera.from_blender(c2w, w, h, camera_angle_x=angle, name=Path(name).stem)
            except InputError as e:
                raise InputError(json_path, f"{where}: {e.problem}") from None
        records.append(FrameRecord(camera=cams[c], time=i / rate, view_id=view, file=video, frame_index=i))
    return records


def load_pinf(root, split: str = "train", *, grayscale: bool = False,
              background_removal: str | None = None) -> FluidDataset:
    root = Path(root)
    json_path = root / INFO
    meta = read_json(json_path)
    key = SPLITS.get(split)
    if key is None:
        raise InputError(json_path, f"unknown split {split!r}; this layout has {', '.join(SPLITS)}")
    entries = meta.get(key)
    if not isinstance(entries, list) or not entries:
        raise InputError(json_path, f"has no {key!r} list (or it is empty)")
    turn = _up_turn(meta, json_path)
    # views are numbered over both lists, so a held-out camera never shares a training camera's id
    first = 0 if split == "train" else len(meta.get("train_videos") or [])
    records = [r for k, e in enumerate(entries) for r in _records(root, e, k, key, json_path, turn, first + k)]
    rates = {e["frame_rate"] for e in entries}  # each checked by _records
    if len(rates) > 1:
        raise InputError(json_path, f"{key}: the videos have different 'frame_rate' values ({sorted(rates)}); "
                                    "the cameras must be synchronised")
    ch = 1 if grayscale else 3
    out = {"layout": "pinf", "time_unit": "seconds", "world_from_file": turn.tolist()}
    box = scene_box(meta, json_path, turn)
    if box is not None:
        out["scene_box"] = box
    return FluidDataset(frames=records, root=root, channels=ch, background=_background(meta, json_path, ch),
                        background_removal=background_removal, meta=out)
