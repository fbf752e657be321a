"""Dataset loaders. ``load_dataset(path)`` detects the layout (``LAYOUTS``, a registry: a new layout
is a module of this package and one entry there):

- ``nerf``: ``path/transforms_{split}.json`` (NeRF / D-NeRF, per-frame ``time``)
- ``neurofluid``: ``path/view_k/transforms_{split}.json``
- ``video``: ``path/cameras.json`` + one video per camera
- ``colmap``: a COLMAP sparse model (``path/sparse/0/cameras.bin`` + ``images.bin``, or .txt) + one
  video per registered image, named by its stem
- ``pinf``: ``path/info.json`` with ``train_videos`` / ``test_videos`` + one video per camera (the
  PINF / HyFluid layout of ScalarFlow captures)
``grayscale=True`` keeps one channel (ScalarFlow-like smoke footage); ``background_removal``
("difference" or "xor") removes the background against each view's first frame. ``resolution``
(a width in pixels) or ``downscale`` (a factor) load the footage smaller, area-averaged
(``FluidDataset.resized``).
"""

from __future__ import annotations

from pathlib import Path

from dataclasses import dataclass
from typing import Callable

from ..errors import InputError
from .colmap import load_colmap, model_folder
from .dataset import FluidDataset, FrameRecord, Sample
from .nerf import load_nerf, load_neurofluid
from .pinf import detect as _pinf_detect, load_pinf
from .video import load_video
from .videos import write_video


@dataclass(frozen=True)
class Layout:
    """A dataset layout: how to recognise it in a folder and how to load one split of it."""

    looks_for: str                                       # what ``detect`` looks for (error messages)
    detect: Callable[[Path, str], bool]                  # (folder, split) -> is it this layout
    load: Callable[..., FluidDataset]                    # (folder, split, fps=, grayscale=, background_removal=)
    splits: bool = True                                  # whether it can hold held-out cameras ("test"): then
                                                         # ``detect`` answers per split


def _neurofluid(path, split, *, fps, grayscale, background_removal):
    ds = load_neurofluid(path, split, fps=fps, grayscale=grayscale)
    ds.background_removal = background_removal
    return ds


# the known layouts, in the order detection tries them
LAYOUTS: dict[str, Layout] = {
    "nerf": Layout("transforms_{split}.json", lambda p, s: (p / f"transforms_{s}.json").exists(),
                   lambda p, s, *, fps, grayscale, background_removal:
                   load_nerf(p, s, grayscale=grayscale, background_removal=background_removal)),
    "neurofluid": Layout("view_*/transforms_{split}.json", lambda p, s: any(p.glob(f"view_*/transforms_{s}.json")),
                         _neurofluid),
    "video": Layout("cameras.json", lambda p, s: (p / "cameras.json").exists(),
                    lambda p, s, *, fps, grayscale, background_removal:
                    load_video(p, grayscale=grayscale, background_removal=background_removal), splits=False),
    "colmap": Layout("a COLMAP sparse/0/", lambda p, s: model_folder(p) is not None,
                     lambda p, s, *, fps, grayscale, background_removal:
                     load_colmap(p, fps=fps, grayscale=grayscale, background_removal=background_removal),
                     splits=False),
    "pinf": Layout("info.json with {split}_videos", _pinf_detect,
                   lambda p, s, *, fps, grayscale, background_removal:
                   load_pinf(p, s, grayscale=grayscale, background_removal=background_removal)),
}


def has_split(path, split: str = "test") -> bool:
    """Whether the dataset folder holds this split (the held-out cameras for "test"), in any layout."""
    path = Path(path)
    return path.is_dir() and any(lay.splits and lay.detect(path, split) for lay in LAYOUTS.values())


def detect_layout(path: Path, split: str = "train") -> str:
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "dataset folder does not exist")
    for name, lay in LAYOUTS.items():
        if lay.detect(path, split):
            return name
    raise InputError(path, "no known dataset layout (looked for "
                           + ", ".join(lay.looks_for.format(split=split) for lay in LAYOUTS.values()) + ")")


def load_dataset(path, *, layout: str = "auto", split: str = "train", grayscale: bool = False,
                 background_removal: str | None = None, fps: float | None = None,
                 duration: float | None = None, resolution: int | None = None,
                 downscale: float | None = None) -> FluidDataset:
    """Load one split. Frame times end up in seconds: a dataset whose ``time_unit`` is
    "normalized" (D-NeRF's [0, 1]) is rescaled by ``duration`` (seconds of the clip) or ``fps``
    (given here or in the dataset); ``meta["time_source"]`` says which was used. ``resolution``
    (width in pixels) or ``downscale`` (a factor >= 1) give smaller images (``FluidDataset.resized``)."""
    path = Path(path)
    if background_removal not in (None, "difference", "xor"):
        raise InputError("background_removal", f"unknown method {background_removal!r}; use 'difference' or 'xor'")
    for name, v in (("fps", fps), ("duration", duration)):
        if v is not None and not (isinstance(v, (int, float)) and v > 0 and v == v and v != float("inf")):
            raise InputError(path, f"--{name} must be a positive number, got {v!r}")
    if layout == "auto":
        layout = detect_layout(path, split)
    if layout not in LAYOUTS:
        raise ValueError(f"unknown dataset layout {layout!r}; choose from auto, {', '.join(LAYOUTS)}")
    if resolution is not None and downscale is not None:
        raise InputError("--downscale", "give --resolution or --downscale, not both")
    if downscale is not None and not (isinstance(downscale, (int, float)) and 1 <= downscale < float("inf")):
        raise InputError("--downscale", f"must be a factor >= 1 (2: half the width and height), got {downscale!r}")
    ds = LAYOUTS[layout].load(path, split, fps=fps, grayscale=grayscale, background_removal=background_removal)
    if resolution is not None:
        ds = ds.resized(width=resolution)
    elif downscale is not None and downscale != 1:
        ds = ds.resized(factor=1.0 / downscale)
    # how the images were read: a reconstruction keeps these, and evaluation reads the held-out views the same way
    ds.meta["dataset_options"] = {k: v for k, v in (("grayscale", grayscale), ("background_removal", background_removal),
                                                    ("resolution", resolution), ("downscale", downscale)) if v}
    return to_seconds(ds, fps=fps, duration=duration)


def to_seconds(ds: FluidDataset, *, fps: float | None = None, duration: float | None = None) -> FluidDataset:
    from dataclasses import replace

    if ds.meta.get("time_unit", "seconds") != "normalized":
        ds.meta.setdefault("time_source", "seconds")
        return ds
    duration = duration or ds.meta.get("duration")
    fps = fps or ds.meta.get("fps")
    times = sorted({f.time for f in ds.frames})
    if duration:
        scale, src = float(duration), f"normalized x duration {duration:g} s"
    elif fps and len(times) > 1:
        scale, src = (len(times) - 1) / float(fps) / max(times[-1] - times[0], 1e-12), \
            f"normalized, {len(times)} frames at {fps:g} fps"
    else:
        ds.meta["time_source"] = "normalized (no fps or duration given: times are clip fractions, not seconds)"
        return ds
    ds.frames = [replace(f, time=f.time * scale) for f in ds.frames]
    ds.meta["time_source"] = src
    ds.meta["time_unit"] = "seconds"
    return ds


def load_grayscale(path, *, layout: str = "auto", split: str = "train",
                   background_removal: str = "difference") -> FluidDataset:
    """Grayscale footage (ScalarFlow-like): one channel, background removed against frame 0."""
    return load_dataset(path, layout=layout, split=split, grayscale=True,
                        background_removal=background_removal)


__all__ = ["FluidDataset", "FrameRecord", "Sample", "load_dataset", "load_grayscale", "load_nerf",
           "load_neurofluid", "load_video", "load_colmap", "load_pinf", "write_video", "detect_layout", "has_split",
           "LAYOUTS"]
