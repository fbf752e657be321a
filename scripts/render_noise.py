"""Diagnostic: how much Monte Carlo noise do a dataset's renders carry?

Compares two renders of the same simulation and cameras (``gf-cli render-dataset`` with another
``--seed`` or ``--samples``), image by image, composited over the dataset's background exactly as
``gf-cli evaluate`` composites its targets, and prints PSNR per frame and split.

    python scripts/render_noise.py DATASET_A DATASET_B [--split test|train|both] [--json FILE]

The ceiling printed holds only for two renders at the same sample count and different seeds:
then the noise of each is half of the MSE between them, so a noise-free prediction of the images
(the best any reconstruction can do) scores PSNR(A, B) + 3 dB against either. Renders that share
a seed share their first samples, so their PSNR overstates how clean either is. Images present in only one of the
two are reported and skipped. Used for BENCHMARKS.md ("2026-12-01 (render noise)"); not part of the API.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gf_core.data import load_dataset  # noqa: E402
from gf_core.eval.evaluate import composited  # noqa: E402


def split_psnr(a_root: str, b_root: str, split: str) -> dict:
    """{time: mean MSE over the views} and per-image rows for one split of two renders."""
    a, b = load_dataset(a_root, split=split), load_dataset(b_root, split=split)
    if a.channels != b.channels:
        raise SystemExit(f"{a_root} has {a.channels} channels, {b_root} {b.channels}")
    bg = torch.as_tensor(np.asarray(a.background, np.float64)[:a.channels], dtype=torch.float32)
    in_b = {(f.view_id, round(f.time, 9)): i for i, f in enumerate(b.frames)}
    per_time: dict = defaultdict(list)
    rows, missing = [], 0
    for i, f in enumerate(a.frames):
        j = in_b.get((f.view_id, round(f.time, 9)))
        if j is None:
            missing += 1
            continue
        x, y = composited(a, i, bg), composited(b, j, bg)
        if x.shape != y.shape:
            raise SystemExit(f"{a.frames[i].file} is {tuple(x.shape)}, {b.frames[j].file} {tuple(y.shape)}")
        mse = float(((x - y) ** 2).mean())
        per_time[f.time].append(mse)
        rows.append({"view": f.view_id, "time": f.time, "psnr": -10 * math.log10(max(mse, 1e-12))})
    if missing:
        print(f"{split}: {missing} images of {a_root} have no counterpart in {b_root} (skipped)")
    return {"per_time": {t: float(np.mean(v)) for t, v in sorted(per_time.items())}, "per_image": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--split", choices=["test", "train", "both"], default="both")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = {"a": args.a, "b": args.b}
    for split in (["test", "train"] if args.split == "both" else [args.split]):
        res = split_psnr(args.a, args.b, split)
        if not res["per_image"]:
            print(f"{split}: no images in common")
            continue
        psnr = {t: -10 * math.log10(max(m, 1e-12)) for t, m in res["per_time"].items()}
        print(f"{split}: time  PSNR(A, B)  ceiling (+3 dB)")
        for t, p in psnr.items():
            print(f"  {t:6.3f}  {p:6.2f}  {p + 3.01:6.2f}")
        v = np.array(list(psnr.values()))
        print(f"{split}: mean over frames {v.mean():.2f} dB (ceiling {v.mean() + 3.01:.2f}), "
              f"worst frame {v.min():.2f} (ceiling {v.min() + 3.01:.2f})")
        out[split] = {"per_frame": [{"time": t, "psnr": p} for t, p in psnr.items()],
                      "psnr_mean": float(v.mean()), "psnr_min_frame": float(v.min()), "per_image": res["per_image"]}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
