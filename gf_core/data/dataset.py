"""The in-memory dataset type that every loader returns.

A dataset is a list of frame records (camera, time in seconds, view id, where the pixels come
from). Pixels are decoded on first access and kept in a byte-bounded cache as the file's own
dtype (uint8 for PNG/video), so opening a 5-view x 100-frame x 400x400 dataset costs a JSON
parse and a few hundred ``stat`` calls, and each image is decoded once.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .images import read_image, to_float

# Open video decoders, shared by every dataset of the process (the datasets that ``with_times`` or
# ``resized`` derive read the same files): each holds the decoder's frame buffers, so only the few
# most recently used stay open, however many datasets there are.
_READERS: OrderedDict = OrderedDict()
MAX_OPEN_VIDEOS = 16


def video_reader(path: Path):
    """The open ``VideoReader`` of ``path`` (opened on first use; the least recently used one is
    closed when more than ``MAX_OPEN_VIDEOS`` are open)."""
    from .videos import VideoReader

    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        raise InputError(path, "video file does not exist (or cannot be read)") from None
    key = (path, st.st_ino, st.st_mtime_ns, st.st_size)  # a file replaced on disk is opened anew
    r = _READERS.get(key)
    if r is None:
        r = _READERS[key] = VideoReader(path)
        while len(_READERS) > MAX_OPEN_VIDEOS:
            _READERS.popitem(last=False)[1].close()
    _READERS.move_to_end(key)
    return r


@dataclass(frozen=True)
class FrameRecord:
    """Where one image comes from: an image file, or frame ``frame_index`` of a video file."""

    camera: Camera
    time: float
    view_id: int
    file: Path
    frame_index: int | None = None  # None: ``file`` is an image; otherwise a video frame
    mask_file: Path | None = None
    distortion: "object" = None     # a ``distortion.Distortion`` of the recording lens, removed at load; None: pinhole
    source: Camera | None = None    # the camera of the file's own pixels when they are resized at load
                                    # (``FluidDataset.resized``); None: used at their own size


@dataclass
class Sample:
    """One training image: ``image`` (H, W, C) float32 in [0, 1] with C = 1 or 3 (straight, not
    premultiplied), ``alpha`` (H, W) or None, ``mask`` (H, W) or None."""

    index: int
    image: "object"
    alpha: "object"
    mask: "object"
    camera: Camera
    time: float
    view_id: int

    def composite(self, background):
        """The image composited over ``background`` (C,) using its alpha (as a renderer sees it)."""
        import torch

        if self.alpha is None:
            return self.image
        bg = torch.as_tensor(background, dtype=self.image.dtype).reshape(1, 1, -1)
        a = self.alpha[..., None]
        return self.image * a + bg * (1.0 - a)


@dataclass
class FluidDataset:
    """Frames of a multiview fluid capture, with lazy decoding.

    ``channels`` is 3 (RGB) or 1 (grayscale: one channel is kept everywhere downstream).
    ``background_removal`` (grayscale footage): None, "difference" (|I - I_first|) or "xor"
    (bitwise XOR of 8-bit values with the view's first frame, as the paper does for ScalarFlow).
    """

    frames: list[FrameRecord]
    root: Path
    channels: int = 3
    background: tuple = (0.0, 0.0, 0.0)
    background_removal: str | None = None
    gt_file: Path | None = None
    meta: dict = field(default_factory=dict)
    cache_bytes: int = 4 << 30

    def __post_init__(self):
        if self.channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {self.channels}")
        if self.background_removal not in (None, "difference", "xor"):
            raise ValueError(f"unknown background_removal {self.background_removal!r}; "
                             "use 'difference' or 'xor'")
        self._cache: OrderedDict = OrderedDict()
        self._cached = 0
        # first frame (earliest time) of each view: the background reference
        first: dict[int, int] = {}
        for i, fr in enumerate(self.frames):
            j = first.get(fr.view_id)
            if j is None or fr.time < self.frames[j].time:
                first[fr.view_id] = i
        self._first_of_view = first

    # ---- summary ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frames)

    @property
    def views(self) -> list[int]:
        return sorted({f.view_id for f in self.frames})

    @property
    def times(self) -> np.ndarray:
        return np.array(sorted({f.time for f in self.frames}), np.float64)

    @property
    def time_range(self) -> tuple[float, float]:
        t = [f.time for f in self.frames]
        return (min(t), max(t)) if t else (0.0, 0.0)

    def cameras(self) -> dict[int, Camera]:
        """One camera per view id (the first frame's)."""
        out: dict[int, Camera] = {}
        for f in self.frames:
            out.setdefault(f.view_id, f.camera)
        return out

    def indices(self, *, view_id: int | None = None, time: float | None = None) -> list[int]:
        return [i for i, f in enumerate(self.frames)
                if (view_id is None or f.view_id == view_id)
                and (time is None or abs(f.time - time) < 1e-9)]

    def select_times(self, frames: slice) -> "FluidDataset":
        """The same images restricted to the times ``self.times[frames]`` (``slice(0, 20)``: the
        first 20; ``slice(None, None, 2)``: every other one). Raises if none is left."""
        ds = self.with_times(self.times[frames])
        ds.meta["frame_selection"] = f"{frames.start or ''}:{frames.stop or ''}:{frames.step or ''}"
        return ds

    def with_times(self, times) -> "FluidDataset":
        """The images at ``times`` (seconds, to 1e-9) only (a new, empty pixel cache)."""
        from dataclasses import replace

        times = np.asarray(times, np.float64).reshape(-1)
        keep = [f for f in self.frames if times.size and np.abs(times - f.time).min() < 1e-9]
        if not keep:
            raise InputError(self.root, f"none of its {len(self.times)} frame times is selected")
        return replace(self, frames=keep, meta=dict(self.meta))

    def resized(self, *, width: int | None = None, factor: float | None = None) -> "FluidDataset":
        """The same frames at another size: ``width`` pixels wide (the height in proportion) or
        ``factor`` times each side (0.25 for ``--downscale 4``). Pixels are area-averaged when
        each image is first decoded (OpenCV's INTER_AREA) and the intrinsics scale with them, so a
        world point projects onto the same image content. Only smaller sizes: upscaling adds no
        information and is refused."""
        from dataclasses import replace

        if (width is None) == (factor is None):
            raise ValueError("give width or factor")
        frames = []
        cams: dict[int, Camera] = {}
        for f in self.frames:
            src = f.source or f.camera
            if width is not None:
                if not isinstance(width, int) or width < 1:
                    raise InputError("--resolution", f"must be a positive number of pixels, got {width!r}")
                k = width / src.width
            else:
                if not (isinstance(factor, (int, float)) and 0 < factor <= 1):
                    raise InputError("--downscale", f"must be a factor >= 1, got {1 / factor if factor else factor!r}")
                k = factor
            if k > 1:
                raise InputError(f.file, f"is {src.width} px wide; --resolution {width} would upscale it "
                                         "(only smaller sizes are allowed)")
            cam = cams.get(id(src))
            if cam is None:
                cam = cams[id(src)] = src.scaled(k)
            frames.append(replace(f, camera=cam, source=None if cam == src else src))
        ds = replace(self, frames=frames, meta=dict(self.meta))
        ds.meta["resolution"] = sorted({(f.camera.width, f.camera.height) for f in frames})
        return ds

    def ground_truth(self):
        """The ground-truth particles (``SimData``) if the dataset carries them, else None."""
        if self.gt_file is None:
            return None
        from ..formats.hdf5 import read_sim

        return read_sim(self.gt_file)

    # ---- pixels ----------------------------------------------------------------------------------
    def _remember(self, key, arr: np.ndarray) -> None:
        self._cache[key] = arr
        self._cache.move_to_end(key)
        self._cached += arr.nbytes
        while self._cached > self.cache_bytes and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cached -= old.nbytes

    def _raw(self, rec: FrameRecord) -> np.ndarray:
        key = (rec.file, rec.frame_index)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        if rec.frame_index is None:
            img = read_image(rec.file)
        else:
            img = video_reader(rec.file).read(rec.frame_index)
            self.__dict__["_decoded"] = self.__dict__.get("_decoded", 0) + 1
        cam = rec.source or rec.camera
        if img.shape[0] != cam.height or img.shape[1] != cam.width:
            raise InputError(rec.file, f"image is {img.shape[1]}x{img.shape[0]} but its camera "
                                       f"says {cam.width}x{cam.height}")
        img = self._to_size(rec, self._undistort(rec, img))
        self._remember(key, img)
        return img

    @staticmethod
    def _to_size(rec: FrameRecord, img: np.ndarray) -> np.ndarray:
        """The decoded pixels area-averaged to the record's camera (``resized``), in their dtype."""
        if rec.source is None:
            return img
        import cv2

        out = cv2.resize(img, (rec.camera.width, rec.camera.height), interpolation=cv2.INTER_AREA)
        return out.reshape(rec.camera.height, rec.camera.width, *img.shape[2:])

    def _undistort(self, rec: FrameRecord, img: np.ndarray) -> np.ndarray:
        """The pinhole image of a recorded one (``gf_core.data.distortion``); one remap table per
        camera and lens, built once."""
        if rec.distortion is None:
            return img
        from .distortion import undistort, undistort_maps

        cam = rec.source or rec.camera
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, rec.distortion)
        maps = self.__dict__.setdefault("_undistort_maps", {})
        if key not in maps:
            maps[key] = undistort_maps(cam, rec.distortion)
        return undistort(img, maps[key])

    @property
    def frames_decoded(self) -> int:
        """Video frames this dataset has decoded so far (images are not counted)."""
        return self.__dict__.get("_decoded", 0)

    @staticmethod
    def _gray(raw: np.ndarray) -> np.ndarray:
        """One channel (Rec. 601 luma for RGB), kept in the file's dtype range."""
        color = raw[:, :, :3] if raw.shape[2] >= 3 else raw[:, :, :1]
        if color.shape[2] == 1:
            return color
        luma = (color.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32))[..., None]
        return np.rint(luma).astype(raw.dtype) if raw.dtype.kind == "u" else luma

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(image (H, W, C) float32 with C = ``channels``, alpha (H, W) or None) as numpy."""
        rec = self.frames[i]
        raw = self._raw(rec)
        alpha = to_float(raw[:, :, 3]) if raw.shape[2] == 4 else None
        color = raw[:, :, :3] if raw.shape[2] >= 3 else raw[:, :, :1]
        if self.channels == 1:
            color = self._gray(raw)
            if self.background_removal is not None:
                color = self._remove_background(rec, color)
        elif color.shape[2] == 1:
            color = np.repeat(color, 3, axis=2)
        return to_float(color), alpha

    def _remove_background(self, rec: FrameRecord, color: np.ndarray) -> np.ndarray:
        ref_rec = self.frames[self._first_of_view[rec.view_id]]
        ref = self._gray(self._raw(ref_rec))
        if self.background_removal == "xor":
            if color.dtype.kind != "u":
                raise InputError(rec.file, "XOR background removal needs integer (8/16-bit) images")
            return np.bitwise_xor(color, ref.astype(color.dtype))
        return np.abs(to_float(color) - to_float(ref.astype(color.dtype)))

    def _mask(self, rec: FrameRecord) -> np.ndarray | None:
        if rec.mask_file is None:
            return None
        m = read_image(rec.mask_file)
        cam = rec.source or rec.camera
        if m.shape[:2] != (cam.height, cam.width):
            raise InputError(rec.mask_file, f"mask is {m.shape[1]}x{m.shape[0]} but its camera says "
                                            f"{cam.width}x{cam.height}")
        m = self._to_size(rec, self._undistort(rec, m))
        return to_float(m[:, :, -1] if m.shape[2] in (2, 4) else m[:, :, 0])

    def __getitem__(self, i: int) -> Sample:
        import torch

        if not -len(self) <= i < len(self):
            raise IndexError(f"frame index {i} out of range for {len(self)} frames")
        i = i % len(self)
        rec = self.frames[i]
        img, alpha = self.load(i)
        mask = self._mask(rec)
        return Sample(index=i, image=torch.from_numpy(img),
                      alpha=None if alpha is None else torch.from_numpy(alpha),
                      mask=None if mask is None else torch.from_numpy(mask),
                      camera=rec.camera, time=rec.time, view_id=rec.view_id)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
