"""Dataset loaders. ``load_dataset(path)`` detects the layout:

- ``nerf``: ``path/transforms_{split}.json`` (NeRF / D-NeRF, per-frame ``time``)
- ``neurofluid``: ``path/view_k/transforms_{split}.json``
- ``video``: ``path/cameras.json`` + one video per camera
``grayscale=True`` keeps one channel (ScalarFlow-like smoke footage); ``background_removal``
("difference" or "xor") removes the background against each view's first frame.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .dataset import FluidDataset, FrameRecord, Sample
from .nerf import load_nerf, load_neurofluid
from .video import load_video, write_video

LAYOUTS = ("nerf", "neurofluid", "video")


def detect_layout(path: Path, split: str = "train") -> str:
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "dataset folder does not exist")
    if (path / f"transforms_{split}.json").exists():
        return "nerf"
    if any(path.glob(f"view_*/transforms_{split}.json")):
        return "neurofluid"
    if (path / "cameras.json").exists():
        return "video"
    raise InputError(path, f"no known dataset layout (looked for transforms_{split}.json, "
                           f"view_*/transforms_{split}.json, cameras.json)")


def load_dataset(path, *, layout: str = "auto", split: str = "train", grayscale: bool = False,
                 background_removal: str | None = None, fps: float | None = None) -> FluidDataset:
    path = Path(path)
    if layout == "auto":
        layout = detect_layout(path, split)
    if layout == "nerf":
        return load_nerf(path, split, grayscale=grayscale, background_removal=background_removal)
    if layout == "neurofluid":
        ds = load_neurofluid(path, split, fps=fps, grayscale=grayscale)
        ds.background_removal = background_removal
        return ds
    if layout == "video":
        return load_video(path, grayscale=grayscale, background_removal=background_removal)
    raise ValueError(f"unknown dataset layout {layout!r}; choose from auto, {', '.join(LAYOUTS)}")


def load_grayscale(path, *, layout: str = "auto", split: str = "train",
                   background_removal: str = "difference") -> FluidDataset:
    """Grayscale footage (ScalarFlow-like): one channel, background removed against frame 0."""
    return load_dataset(path, layout=layout, split=split, grayscale=True,
                        background_removal=background_removal)


__all__ = ["FluidDataset", "FrameRecord", "Sample", "load_dataset", "load_grayscale", "load_nerf",
           "load_neurofluid", "load_video", "write_video", "detect_layout", "LAYOUTS"]
