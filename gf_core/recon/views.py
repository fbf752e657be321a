"""The training (and held-out) views: every image of a split decoded once onto the training
device, with its alpha, camera, time and view, and what a step compares with (``composite``)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from ..render import render
from .terms.image import psnr


@dataclass
class Views:
    """Decoded images of one split, on the training device."""

    images: list          # (H, W, C) float32
    alphas: list          # (H, W) or None
    cameras: list
    times: np.ndarray     # seconds
    view_ids: list
    background: torch.Tensor
    channels: int         # 3 (RGB) or 1 (grayscale)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def unique_times(self) -> np.ndarray:
        return np.unique(self.times)

    def at_time(self, t: float) -> list[int]:
        if not hasattr(self, "_by_time"):
            self._by_time = {}
            for i, ti in enumerate(self.times):
                self._by_time.setdefault(round(float(ti), 9), []).append(i)
        return list(self._by_time.get(round(float(t), 9), []))

    def target(self, i: int, bg: torch.Tensor) -> torch.Tensor:
        """Image ``i`` as the renderer should reproduce it over background ``bg``: composited by its
        alpha, or as it is without one (then against the dataset's own background)."""
        return composite(self.images[i], self.alphas[i], bg)


def load_views(ds, device, dtype=torch.float32) -> Views:
    imgs, alphas, cams, times, views = [], [], [], [], []
    for i in range(len(ds)):
        img, alpha = ds.load(i)
        if not np.all(np.isfinite(img)):
            raise InputError(ds.frames[i].file, "image contains NaN or infinite values")
        imgs.append(torch.as_tensor(img, dtype=dtype, device=device))
        alphas.append(None if alpha is None else torch.as_tensor(alpha, dtype=dtype, device=device))
        rec = ds.frames[i]
        cams.append(rec.camera)
        times.append(rec.time)
        views.append(rec.view_id)
    bg = torch.as_tensor(np.asarray(ds.background, np.float64)[:ds.channels], dtype=dtype, device=device)
    return Views(imgs, alphas, cams, np.asarray(times, np.float64), views, bg, int(ds.channels))


@torch.no_grad()
def heldout_psnr(model, test: Views | None, *, decoded: bool, frames: int) -> float | None:
    """Mean PSNR of ``model`` in the held-out views ``test`` at ``frames`` of their times spread
    over the clip (decoded at each time, or the canonical particles when not ``decoded``); None
    without held-out views."""
    if test is None:
        return None
    times = test.unique_times
    pick = times[np.unique(np.linspace(0, len(times) - 1, min(frames, len(times))).round().astype(int))]
    vals = []
    for t in pick:
        p = model.at(float(t) if decoded else None)
        for i in test.at_time(float(t)):
            out = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], test.cameras[i],
                         test.background, sh_degree=model.sh_degree)
            vals.append(psnr(out.color, test.target(i, test.background)))
    return float(np.mean(vals)) if vals else None


def composite(img: torch.Tensor, alpha: torch.Tensor | None, bg: torch.Tensor) -> torch.Tensor:
    """An (H, W, C) image over the background colour ``bg`` (C,) by its alpha (H, W); as it is
    without alpha."""
    if alpha is None:
        return img
    a = alpha[..., None]
    return img * a + bg.reshape(1, 1, -1) * (1 - a)


def composited(ds, i: int, bg: torch.Tensor) -> torch.Tensor:
    """Image ``i`` of dataset ``ds``, decoded now, over the background ``bg`` (C,) on ``bg``'s
    device: what a rendering is compared with outside training (evaluation, in-between frames)."""
    img, alpha = ds.load(i)
    return composite(torch.as_tensor(img, device=bg.device),
                     None if alpha is None else torch.as_tensor(alpha, device=bg.device), bg)


def dataset_fingerprint(ds) -> str:
    """A hash of what the images are (files, sizes, mtimes, cameras, times)."""
    h = hashlib.sha1()
    for f in ds.frames:
        st = os.stat(f.file)
        h.update(f"{f.file}|{st.st_size}|{st.st_mtime_ns}|{f.time}|{f.view_id}|{f.frame_index}".encode())
        h.update(np.asarray(f.camera.world_to_camera).tobytes())
    return h.hexdigest()[:16]


__all__ = ["Views", "load_views", "heldout_psnr", "composite", "composited", "dataset_fingerprint"]
