"""Video files: their size and rate, frames decoded one at a time (``VideoReader``), and a
lossless writer. Shared by the layouts that read videos (``video``, ``colmap``) and the dataset's
lazy frame decoding."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError


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
