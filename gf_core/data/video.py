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

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .dataset import FluidDataset, FrameRecord
from .distortion import from_keys as distortion_from_keys
from .nerf import _background, _num, intrinsics, path_value, read_json, view_id


def video_info(path: Path) -> tuple[int, int, int, float]:
    """(frame count, width, height, fps) from the container, without decoding."""
    import cv2

    if not Path(path).exists():
        raise InputError(path, "video file does not exist")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise InputError(path, "OpenCV cannot open this video (corrupt or unsupported codec)")
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    if n <= 0 or w <= 0 or h <= 0:
        raise InputError(path, f"video reports {n} frames of {w}x{h}; cannot use it")
    return n, w, h, fps


def decode_video(path: Path) -> list[np.ndarray]:
    """All frames of a video as (H, W, 3) uint8 RGB arrays."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(path, "OpenCV cannot open this video (corrupt or unsupported codec)")
    frames = []
    try:
        while True:
            ok, fr = cap.read()
            if not ok:
                break
            frames.append(np.ascontiguousarray(fr[:, :, ::-1]))
    finally:
        cap.release()
    if not frames:
        raise InputError(path, "video decodes to no frames")
    return frames


class VideoReader:
    """Random access to one video's frames without decoding it whole: frames are read in order
    while requests follow each other, and the decoder seeks (``CAP_PROP_POS_FRAMES``) on a jump,
    so interleaved multiview access costs about one decoded frame per request, not one video.
    ``frames_decoded`` counts what was decoded (tests hold it to that)."""

    def __init__(self, path: Path):
        import cv2

        self.path = Path(path)
        self.cap = cv2.VideoCapture(str(self.path))
        if not self.cap.isOpened():
            raise InputError(self.path, "OpenCV cannot open this video (corrupt or unsupported codec)")
        self.next = 0
        self.frames_decoded = 0

    def read(self, k: int) -> np.ndarray:
        import cv2

        if k != self.next:
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, int(k))
            self.next = int(k)
        ok, fr = self.cap.read()
        if not ok:
            raise InputError(self.path, f"frame {k} cannot be decoded (the video is shorter than its container "
                                        "says, or truncated)")
        self.frames_decoded += 1
        self.next = k + 1
        return np.ascontiguousarray(fr[:, :, ::-1])

    def close(self) -> None:
        self.cap.release()


def write_video(path: Path, frames, fps: float) -> Path:
    """Write RGB uint8 frames losslessly (FFV1 in .mkv/.avi); used by tests and exporters."""
    import cv2

    path = Path(path)
    frames = [np.asarray(f) for f in frames]
    h, w = frames[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), float(fps), (w, h))
    if not wr.isOpened():
        raise InputError(path, "OpenCV cannot open a FFV1 video writer for this path")
    try:
        for f in frames:
            if f.shape[:2] != (h, w):
                raise InputError(path, "all frames of a video must have the same size")
            f = f if f.ndim == 3 and f.shape[2] == 3 else np.repeat(f.reshape(h, w, 1), 3, axis=2)
            wr.write(np.ascontiguousarray(f[:, :, ::-1]))
    finally:
        wr.release()
    return path


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
        ew, eh = _num(entry, "w", json_path, where), _num(entry, "h", json_path, where)
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
    fps_all = _num(meta, "fps", json_path, "top level")
    t0 = _num(meta, "start_time", json_path, "top level") or 0.0
    records = video_records(root, cams, json_path, fps=fps_all, start_time=t0)
    ch = 1 if grayscale else 3
    bg = _background({"background": meta.get("background", 0.0)}, ch, json_path)
    return FluidDataset(frames=records, root=root, channels=ch, background=bg,
                        background_removal=background_removal,
                        meta={"layout": "video"})
