"""Multiview video datasets: one video file per camera plus ``cameras.json``.

cameras.json:
  {"fps": 30 (optional; default: each video's own), "start_time": 0.0 (optional),
   "cameras": [{"video": "cam0.mkv", "view_id": 0,
                "transform_matrix": 4x4 camera-to-world, OpenGL (Blender/NeRF), or
                "world_to_camera": 4x4, OpenCV,
                "fl_x" [, "fl_y"] or "camera_angle_x", "cx", "cy" (default W/2, H/2),
                "w", "h" (optional; checked against the video),
                "pixel_center": "half" (default: NeRF, centres at +0.5) or "integer" (OpenCV
                calibration: cx, cy get +0.5),
                "camera_model", "k1" ... "p2" (optional lens distortion, as in nerfstudio's
                transforms.json; removed when frames are decoded, ``distortion``)}]}
Frame k of a video has time start_time + k / fps. Frames are decoded with OpenCV on first use.
"""

from __future__ import annotations

from pathlib import Path

from ..camera import Camera
from ..errors import InputError
from .dataset import FluidDataset, FrameRecord
from .distortion import from_keys as distortion_from_keys
from .fields import background, intrinsics, number, path_value, read_json, view_id
from .videos import video_info


def _camera(entry: dict, w: int, h: int, json_path: Path, where: str) -> Camera:
    fx, fy, angle, _, cx, cy = intrinsics(entry, json_path, where)
    shift = 0.5 if entry.get("pixel_center", "half") == "integer" else 0.0
    cx = None if cx is None else cx + shift
    cy = None if cy is None else cy + shift
    name = str(entry.get("name", ""))
    try:
        if "transform_matrix" in entry:
            return Camera.from_blender(entry["transform_matrix"], w, h, fx=fx, fy=fy, cx=cx, cy=cy,
                                       camera_angle_x=angle, name=name)
        if "world_to_camera" in entry:
            fx = fx if fx is not None else Camera.focal_from_angle(angle, w)
            fy = fy if fy is not None else fx
            return Camera(fx, fy, w / 2 if cx is None else cx, h / 2 if cy is None else cy, w, h,
                          entry["world_to_camera"], name=name)
    except InputError as e:
        raise InputError(json_path, f"{where}: {e.problem}") from None
    raise InputError(json_path, f"{where}: needs 'transform_matrix' (OpenGL camera-to-world) or "
                                "'world_to_camera' (OpenCV)")


def video_records(root: Path, cams: list, json_path: Path, *, fps: float | None,
                  start_time: float, fps_hint: str | None = None) -> list[FrameRecord]:
    """Frame records of every camera entry (``cameras.json`` keys; errors name ``json_path``):
    frame k of a camera's video at start_time + k / fps (``fps`` or the video's own rate)."""
    records: list[FrameRecord] = []
    for k, entry in enumerate(cams):
        where = f"camera {k}"
        if not isinstance(entry, dict) or entry.get("video") is None:
            raise InputError(json_path, f"{where}: missing 'video'")
        video = root / path_value(entry, "video", json_path, where)
        n, w, h, fps_file = video_info(video)
        ew, eh = number(entry, "w", json_path, where), number(entry, "h", json_path, where)
        if (ew is not None and int(ew) != w) or (eh is not None and int(eh) != h):
            raise InputError(video, f"video is {w}x{h} but {json_path.name} says "
                                    f"{int(ew or w)}x{int(eh or h)}")
        rate = fps or fps_file
        if not rate or rate <= 0:
            raise InputError(video, "video has no frame rate; " + (fps_hint or f"give 'fps' in {json_path.name}"))
        cam = _camera(entry, w, h, json_path, where)
        view = view_id(entry, json_path, where, default=k)
        dist = distortion_from_keys(entry, json_path, where)
        records.extend(FrameRecord(camera=cam, time=start_time + i / rate, view_id=view, file=video,
                                   frame_index=i, distortion=dist) for i in range(n))
    return records


def load_video(root, *, cameras_file: str = "cameras.json", grayscale: bool = False,
               background_removal: str | None = None) -> FluidDataset:
    root = Path(root)
    json_path = root / cameras_file
    meta = read_json(json_path)
    cams = meta.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise InputError(json_path, "has no 'cameras' list (or it is empty)")
    fps_all = number(meta, "fps", json_path, "top level")
    t0 = number(meta, "start_time", json_path, "top level") or 0.0
    records = video_records(root, cams, json_path, fps=fps_all, start_time=t0)
    ch = 1 if grayscale else 3
    bg = background({"background": meta.get("background", 0.0)}, ch, json_path)
    return FluidDataset(frames=records, root=root, channels=ch, background=bg,
                        background_removal=background_removal,
                        meta={"layout": "video"})
