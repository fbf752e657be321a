"""NeRF / D-NeRF ``transforms_{split}.json`` datasets, and the NeuroFluid per-view layout.

transforms_{split}.json (top level, each key may be overridden per frame):
  camera_angle_x | fl_x [fl_y] ; cx, cy (default W/2, H/2) ; w, h (default: the image's size)
  camera_model, k1 k2 k3 k4 p1 p2 (nerfstudio's lens distortion, OPENCV or OPENCV_FISHEYE):
  removed when the images are loaded (``distortion``)
  fps (optional): time = frame_index / fps for frames without "time"
  frames: [{file_path, transform_matrix (camera-to-world, OpenGL), time (seconds), view_id?,
            mask_path?, time_s?}]
  time_s (D-NeRF exports that normalise ``time`` to [0, 1]): the frame's time in seconds; when
  every frame carries one it is the frame's time, whatever ``time`` and ``time_unit`` say.
View ids: a frame's ``view_id`` (or ``camera_id``); otherwise frames with the same
transform_matrix share a view, numbered in order of first appearance.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .dataset import FluidDataset, FrameRecord
from .distortion import from_keys as distortion_from_keys
from .fields import background, intrinsics, matrix_value, number, path_value, read_json, view_id
from .images import image_size

_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp")


def resolve_image(root: Path, file_path: str, json_path: Path, what: str = "image") -> Path:
    p = (root / file_path).resolve() if not Path(file_path).is_absolute() else Path(file_path)
    if p.exists() and p.is_file():
        return p
    if not p.suffix or p.suffix.lower() not in _IMAGE_EXTS:
        for ext in _IMAGE_EXTS:
            q = p.with_name(p.name + ext)
            if q.exists():
                return q
    raise InputError(p, f"{what} listed in {json_path} does not exist")


def parse_transforms(json_path: Path, *, view_offset: int = 0, fixed_view: int | None = None,
                     fps: float | None = None, time_from_index: bool = False,
                     check_sizes: bool = True, known_views: dict | None = None):
    """Frame records from one transforms JSON. Returns (records, json dict).

    A frame's view id comes from ``view_id``, ``view`` or ``camera_id`` (first found), else from its
    pose (frames with the same pose share one); ``known_views`` (pose bytes -> id) gives poses
    already numbered (the training split's) their ids."""
    json_path = Path(json_path)
    meta = read_json(json_path)
    root = json_path.parent
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(json_path, "has no 'frames' list (or it is empty)")
    fps = number(meta, "fps", json_path, "top level") or fps
    with_s = sum(isinstance(fr, dict) and "time_s" in fr for fr in frames)
    if 0 < with_s < len(frames):
        raise InputError(json_path, f"{with_s} of its {len(frames)} frames carry 'time_s' (seconds): give it for "
                                    "every frame or for none")
    records: list[FrameRecord] = []
    view_of_pose: dict[bytes, int] = {}
    for k, fr in enumerate(frames):
        where = f"frame {k}"
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise InputError(json_path, f"{where}: missing 'file_path'")
        if "transform_matrix" not in fr:
            raise InputError(json_path, f"{where}: missing 'transform_matrix'")
        c2w = matrix_value(fr["transform_matrix"], json_path, where, "transform_matrix")
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        file_path = path_value(fr, "file_path", json_path, where)
        if file_path is None:
            raise InputError(json_path, f"{where}: 'file_path' is null")
        img = resolve_image(root, file_path, json_path)
        merged = {**meta, **fr}
        w, h = number(merged, "w", json_path, where), number(merged, "h", json_path, where)
        size = image_size(img) if (check_sizes or w is None or h is None) else None
        if w is None or h is None:
            if size is None:
                from .images import read_image

                arr = read_image(img)
                size = (arr.shape[1], arr.shape[0])
            w, h = size
        elif size is not None and size != (int(w), int(h)):
            raise InputError(img, f"image is {size[0]}x{size[1]} but {json_path.name} says "
                                  f"{int(w)}x{int(h)}")
        fx, fy, angle, angle_y, cx, cy = intrinsics(merged, json_path, where)
        try:
            cam = Camera.from_blender(c2w, int(w), int(h), fx=fx, fy=fy, cx=cx, cy=cy,
                                      camera_angle_x=angle, camera_angle_y=angle_y,
                                      name=str(fr.get("camera_name", "")))
        except InputError as e:
            raise InputError(json_path, f"{where}: {e.problem}") from None
        t = number(fr, "time_s" if with_s else "time", json_path, where)
        if t is None:
            fidx = number(fr, "frame", json_path, where)
            if fidx is not None and fps:
                t = fidx / fps
            elif time_from_index and fps:
                t = k / fps
            else:
                raise InputError(json_path, f"{where}: no 'time' (and no 'frame' with a top-level 'fps')")
        key = np.round(c2w, 6).tobytes()
        explicit = view_id(fr, json_path, where)
        if fixed_view is not None:
            view = fixed_view
        elif known_views is not None and key in known_views:
            view = known_views[key]  # the same pose as a training camera: the same view
        elif explicit is not None:
            view = explicit + view_offset
        else:
            view = view_of_pose.setdefault(key, len(view_of_pose) + view_offset)
        mask = path_value(fr, "mask_path", json_path, where)
        mask = resolve_image(root, mask, json_path, "mask") if mask else None
        records.append(FrameRecord(camera=cam, time=t, view_id=view, file=img, mask_file=mask,
                                   distortion=distortion_from_keys(merged, json_path, where)))
    if with_s:  # seconds already: no rescaling of a normalised "time"
        meta = {**meta, "time_unit": "seconds", "time_source": "time_s (seconds per frame)"}
    return records, meta


def _gt_file(root: Path, meta: dict, json_path: Path) -> Path | None:
    name = path_value(meta, "gt_particles", json_path, "top level")
    if name:
        p = root / name
        if not p.exists():
            raise InputError(json_path, f"'gt_particles' names {p}, which does not exist")
        return p
    p = root / "gt_sim.h5"
    return p if p.exists() else None


TIME_UNITS = ("seconds", "normalized")


def dataset_meta(meta: dict, json_path: Path) -> dict:
    """The documented top-level keys a reconstruction uses: ``scene_box`` [[x0,y0,z0],[x1,y1,z1]]
    (metres), ``floor`` (the floor's height alone, metres), ``time_unit`` ("seconds", default, or "normalized": D-NeRF's [0, 1] clip time),
    ``fps`` and ``duration`` (seconds of the clip, for normalised time)."""
    out = {}
    if "scene_box" in meta:
        box = np.asarray(meta["scene_box"], dtype=object)
        try:
            a = np.asarray(meta["scene_box"], np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != (2, 3) or not np.all(np.isfinite(a)) or np.any(a[1] <= a[0]):
            raise InputError(json_path, f"'scene_box' must be [[x0, y0, z0], [x1, y1, z1]] with max > min, "
                                        f"got {box.tolist()}")
        out["scene_box"] = a.tolist()
    if "floor" in meta:
        z = number(meta, "floor", json_path, "top level")
        if z is None:
            raise InputError(json_path, f"'floor' must be a finite number (the floor's height, metres), got {meta['floor']!r}")
        out["floor"] = z
    if "gt_density" in meta:  # a smoke dataset's true density per frame (a grid.h5 beside it)
        name = path_value(meta, "gt_density", json_path, "top level")
        p = json_path.parent / name
        if not p.exists():
            raise InputError(json_path, f"'gt_density' names {p}, which does not exist")
        out["gt_density"] = str(p)
    unit = meta.get("time_unit", "seconds")
    if unit == "normalised":
        unit = "normalized"
    if unit not in TIME_UNITS:
        raise InputError(json_path, f"'time_unit' must be one of {', '.join(TIME_UNITS)}, got {unit!r}")
    out["time_unit"] = unit
    if "time_source" in meta:
        out["time_source"] = str(meta["time_source"])
    for k in ("fps", "duration"):
        v = number(meta, k, json_path, "top level")
        if v is not None:
            if v <= 0:
                raise InputError(json_path, f"'{k}' must be positive, got {v}")
            out[k] = v
    return out


def load_nerf(root, split: str = "train", *, grayscale: bool = False,
              background_removal: str | None = None) -> FluidDataset:
    """A D-NeRF style dataset: ``root/transforms_{split}.json`` with per-frame ``time``."""
    root = Path(root)
    json_path = root / f"transforms_{split}.json"
    known, offset = None, 0
    train_json = root / "transforms_train.json"
    if split != "train" and train_json.exists():
        # held-out cameras never take a training camera's id: same pose -> same id, others after
        train_recs, _ = parse_transforms(train_json, check_sizes=False)
        known = {np.round(r.camera.to_blender_c2w(), 6).tobytes(): r.view_id for r in train_recs}
        offset = max(r.view_id for r in train_recs) + 1
    records, meta = parse_transforms(json_path, known_views=known)
    if known is not None:
        train_ids = set(known.values())
        pose_of = {r.view_id: np.round(r.camera.to_blender_c2w(), 6).tobytes() for r in records}
        clash = {v for v, k in pose_of.items() if v in train_ids and known.get(k) != v}
        if clash:
            records = [replace(r, view_id=r.view_id + offset) if r.view_id in clash else r for r in records]
    ch = 1 if grayscale else 3
    return FluidDataset(frames=records, root=root, channels=ch,
                        background=background(meta, ch, json_path), background_removal=background_removal,
                        gt_file=_gt_file(root, meta, json_path),
                        meta={"layout": "nerf", "split": split, **dataset_meta(meta, json_path)})


def load_neurofluid(root, split: str = "train", *, fps: float | None = None,
                    grayscale: bool = False) -> FluidDataset:
    """The NeuroFluid layout: ``root/view_k/transforms_{split}.json``, one camera per folder.

    Frames without ``time`` get time = index / fps; with no fps given the clip is taken to span
    one second (the NeuroFluid scenes are one-second clips): time = index / (n_frames - 1).
    """
    root = Path(root)
    view_dirs = sorted((d for d in root.glob("view_*") if d.is_dir()),
                       key=lambda d: int(d.name.split("_")[1]) if d.name.split("_")[1].isdigit() else 1 << 30)
    if not view_dirs:
        raise InputError(root, "no view_k/ folders found (NeuroFluid layout)")
    records: list[FrameRecord] = []
    gt = None
    for d in view_dirs:
        try:
            k = int(d.name.split("_")[1])
        except ValueError:
            raise InputError(d, "view folder name must be view_<integer>") from None
        json_path = d / f"transforms_{split}.json"
        meta = read_json(json_path)
        n = len(meta.get("frames") or [])
        view_fps = fps or number(meta, "fps", json_path, "top level") or max(n - 1, 1)
        if view_fps <= 0:
            raise InputError(json_path, f"'fps' must be positive, got {view_fps}")
        # NeuroFluid frames carry no time: they are numbered in file order
        recs, meta = parse_transforms(json_path, fixed_view=k, fps=view_fps, time_from_index=True)
        records.extend(recs)
        gt = gt or _gt_file(d, meta, json_path)
    ch = 1 if grayscale else 3
    return FluidDataset(frames=records, root=root, channels=ch, gt_file=gt or _gt_file(root, {}, root),
                        meta={"layout": "neurofluid", "split": split})
