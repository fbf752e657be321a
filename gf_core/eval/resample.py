"""Temporal resampling (paper Sec. 4.3.2, Table 7): render the training views at K x the source
frame rate from the continuous decoder, score the frames held out in time, and measure jitter.

Two baselines a video gives without any reconstruction, built from the source (training) frames'
images: *frame repetition* (each in-between frame is the nearest earlier source frame) and
*linear blending* (each in-between frame mixes its two neighbouring source frames by time).

- Held-out frames: the dataset's frames whose times were not trained on (``gf-cli reconstruct
  --frames ::2`` trains on every other frame) and lie inside the trained clip; PSNR/SSIM of the
  decoder's render and of both baselines against the true image.
- Jitter (Table 7): the standard deviation of the per-pixel differences between adjacent frames
  of the K x sequence, over all pixels, frames and training views. Where the dataset has true
  images at every time of the K x grid, their jitter is reported too (the reference).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..recon.views import composited
from ..render import render
from .metrics import image_metrics

METHODS = ("decoder", "repetition", "blend")


class _Jitter:
    """Running standard deviation of adjacent-frame differences (streamed: no sequence in memory)."""

    def __init__(self):
        self.n, self.s, self.s2, self.prev = 0, 0.0, 0.0, None

    def add(self, img: np.ndarray) -> None:
        if self.prev is not None:
            d = img.astype(np.float64) - self.prev
            self.n += d.size
            self.s += float(d.sum())
            self.s2 += float((d * d).sum())
        self.prev = img.astype(np.float64)

    def end_sequence(self) -> None:
        self.prev = None

    def value(self) -> float:
        if self.n == 0:
            return float("nan")
        m = self.s / self.n
        return float(np.sqrt(max(self.s2 / self.n - m * m, 0.0)))


def _neighbours(src: np.ndarray, t: float) -> tuple[int, int, float]:
    """Indices of the source times around ``t`` and the blend weight of the later one."""
    j = int(np.searchsorted(src, t, side="right"))
    a, b = max(j - 1, 0), min(j, len(src) - 1)
    w = 0.0 if b == a else float((t - src[a]) / (src[b] - src[a]))
    return a, b, min(max(w, 0.0), 1.0)


def upsample(model, recon, ds, k: int, *, out: Path | None = None, device="cpu", log=print,
             save_views: int = 1) -> dict:
    """Temporal resampling of ``model`` (a dynamic ``FluidModel`` from ``recon``) against the
    training-view dataset ``ds`` at ``k`` x the source frame rate. With ``out``, the K x frames of
    the first ``save_views`` views are written as PNGs under ``out/upsample_x{k}/view_<id>/``."""
    from ..data.images import write_png

    if k < 1:
        raise InputError("--upsample", f"must be an integer >= 1, got {k}")
    if not model.is_dynamic:
        raise InputError("--upsample", "the reconstruction is static (no decoder): nothing to resample in time")
    src = np.asarray(recon.config.get("frame_times_s") or [], np.float64)
    if src.size < 2:
        raise InputError("--upsample", "the reconstruction records fewer than 2 training frame times "
                                       "(config frame_times_s); reconstruct it again with this toolkit")
    step = float(np.median(np.diff(src))) / k
    grid = src[0] + step * np.arange(int(round((src[-1] - src[0]) / step)) + 1)
    bg = np.asarray(ds.background, np.float64)[:ds.channels].astype(np.float32)
    bg_t = torch.as_tensor(bg, device=device)
    all_times = ds.times

    def has(times, t):
        return times.size and np.abs(times - t).min() < 1e-6 * max(step, 1e-9)

    held = [t for t in all_times if not has(src, t) and src[0] < t < src[-1]]
    cache = {}

    def decoded(t):
        if t not in cache:
            cache.clear()
            with torch.no_grad():
                cache[t] = model.at(float(t))
        return cache[t]

    def rendered(t, cam):
        p = decoded(t)
        with torch.no_grad():
            o = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], cam, bg_t,
                       sh_degree=model.sh_degree)
        return o.color.cpu().numpy()

    def image_at(view, t):
        idx = ds.indices(view_id=view, time=float(t))
        return composited(ds, idx[0], torch.as_tensor(bg)).numpy() if idx else None

    # held-out frames: decoder vs repetition vs blending, against the truth
    rows = []
    for t in held:
        a, b, w = _neighbours(src, t)
        for view in ds.views:
            truth, ia, ib = image_at(view, t), image_at(view, src[a]), image_at(view, src[b])
            if truth is None or ia is None or ib is None:
                continue
            cam = ds.frames[ds.indices(view_id=view, time=float(t))[0]].camera
            tt = torch.as_tensor(truth)
            row = {"time": float(t), "view": view}
            for name, img in (("decoder", rendered(t, cam)), ("repetition", ia), ("blend", (1 - w) * ia + w * ib)):
                m = image_metrics(torch.as_tensor(img), tt)
                row[f"{name}_psnr"], row[f"{name}_ssim"] = m["psnr"], m["ssim"]
            rows.append(row)
    result = {"k": k, "source_fps": 1.0 / (step * k), "fps": 1.0 / step, "frames": int(grid.size),
              "heldout_times": [float(t) for t in held], "heldout_images": len(rows)}
    if rows:
        result["heldout"] = {m: {"psnr": float(np.mean([r[f"{m}_psnr"] for r in rows])),
                                 "ssim": float(np.mean([r[f"{m}_ssim"] for r in rows]))} for m in METHODS}
        result["heldout"]["per_image"] = rows

    # jitter over the K x sequence of every training view
    jit = {m: _Jitter() for m in METHODS}
    truth_jit, truth_complete = _Jitter(), True
    save = out / f"upsample_x{k}" if out is not None else None
    for vi, view in enumerate(ds.views):
        idx0 = ds.indices(view_id=view)
        if not idx0:
            continue
        cam = ds.frames[idx0[0]].camera
        src_imgs = [image_at(view, t) for t in src]
        if any(im is None for im in src_imgs):
            continue
        for g, t in enumerate(grid):
            a, b, w = _neighbours(src, t)
            dec = rendered(t, cam)
            jit["decoder"].add(dec)
            jit["repetition"].add(src_imgs[a] if w < 1.0 else src_imgs[b])
            jit["blend"].add((1 - w) * src_imgs[a] + w * src_imgs[b])
            truth = image_at(view, t) if has(all_times, t) else None
            truth_complete &= truth is not None
            if truth is not None:
                truth_jit.add(truth)
            if save is not None and vi < save_views:
                write_png(save / f"view_{view:02d}" / f"{g:04d}.png", np.clip(dec, 0, 1))
        for j in (*jit.values(), truth_jit):
            j.end_sequence()
    result["jitter"] = {m: jit[m].value() for m in METHODS}
    if truth_complete:
        result["jitter"]["truth"] = truth_jit.value()
    if save is not None:
        result["frames_dir"] = str(save)
    h = result.get("heldout")
    log(f"upsample x{k} ({result['source_fps']:.4g} -> {result['fps']:.4g} fps, {grid.size} frames): jitter decoder "
        f"{result['jitter']['decoder']:.4f}, repetition {result['jitter']['repetition']:.4f}, blend "
        f"{result['jitter']['blend']:.4f}" + (f", truth {result['jitter']['truth']:.4f}" if "truth" in result["jitter"] else "")
        + (f"; held out in time ({len(held)} frames): PSNR decoder {h['decoder']['psnr']:.2f}, repetition "
           f"{h['repetition']['psnr']:.2f}, blend {h['blend']['psnr']:.2f} dB" if h else "; no frame held out in time"))
    return result


__all__ = ["upsample", "METHODS"]
