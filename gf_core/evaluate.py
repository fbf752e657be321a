"""``gf-cli evaluate``: judge a reconstruction by what the images, the physics and (when known)
the true particles say, per split, view and frame; writes ``eval.json`` and PNG plots.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from .errors import InputError
from .io import atomic_write_text, read_recon, read_sim
from .metrics import density_spread, image_metrics, particle_error
from .model import FluidModel
from .render import render


def _render_split(model: FluidModel, ds, device) -> list[dict]:
    rows = []
    bg = torch.as_tensor(np.asarray(ds.background, np.float64)[:ds.channels], dtype=torch.float32, device=device)
    cache_t, params = None, None
    order = sorted(range(len(ds)), key=lambda i: ds.frames[i].time)
    for i in order:
        rec = ds.frames[i]
        if cache_t != rec.time:
            with torch.no_grad():
                params = model.at(rec.time)
            cache_t = rec.time
        img, alpha = ds.load(i)
        target = torch.as_tensor(img, device=device)
        if alpha is not None:
            a = torch.as_tensor(alpha, device=device)[..., None]
            target = target * a + bg.reshape(1, 1, -1) * (1 - a)
        with torch.no_grad():
            out = render(params["means"], params["scales"], params["quats"], params["opacities"], params["sh"],
                         rec.camera, bg, sh_degree=model.sh_degree)
        m = image_metrics(out.color, target)
        rows.append({"view": rec.view_id, "time": rec.time, **m})
    return rows


def _summary(rows: list[dict]) -> dict:
    if not rows:
        return {}
    times = sorted({r["time"] for r in rows})
    per_frame = [{"time": t, "psnr": float(np.mean([r["psnr"] for r in rows if r["time"] == t])),
                  "ssim": float(np.mean([r["ssim"] for r in rows if r["time"] == t]))} for t in times]
    finite = [r["psnr"] for r in rows if math.isfinite(r["psnr"])]
    return {"psnr_mean": float(np.mean(finite)) if finite else math.inf,
            "ssim_mean": float(np.mean([r["ssim"] for r in rows])),
            "psnr_min_frame": float(min(f["psnr"] for f in per_frame)),
            "per_frame": per_frame, "per_image": rows}


def evaluate(run: Path, *, dataset=None, test_dataset=None, gt_path=None, device="cpu", out: Path | None = None,
             log=print) -> dict:
    run = Path(run)
    recon_path = run / "recon.h5" if run.is_dir() else run
    out = Path(out) if out else (run if run.is_dir() else run.parent)
    r = read_recon(recon_path)
    model = FluidModel.from_recon(r, device=device)
    result = {"recon": str(recon_path), "particles": len(model), "dynamic": model.is_dynamic}
    if dataset is not None:
        for name, ds in (("train", dataset), ("test", test_dataset)):
            if ds is None or len(ds) == 0:
                continue
            if ds.channels != model.channels:
                raise InputError(ds.root, f"{ds.channels}-channel images for a {model.channels}-channel reconstruction")
            result[name] = _summary(_render_split(model, ds, device))
            log(f"{name}: PSNR {result[name]['psnr_mean']:.2f} dB, SSIM {result[name]['ssim_mean']:.3f} "
                f"over {len(ds)} images (worst frame {result[name]['psnr_min_frame']:.2f} dB)")
    # physics: the SPH density spread per frame
    times = np.unique([f.time for f in dataset.frames]) if dataset is not None else \
        np.linspace(model.time_map.t_min, model.time_map.t_max, 10 if model.is_dynamic else 1)
    h = float(r.config.get("h") or 2.5 * (r.config.get("spacing") or 1.0))
    dens = []
    for t in times:
        with torch.no_grad():
            p = model.at(float(t))["means"]
        dens.append({"time": float(t), **density_spread(p, h)})
    result["density"] = {"h": h, "per_frame": dens, "std_mean": float(np.mean([d["std"] for d in dens]))}
    log(f"SPH density D_i / mean: standard deviation {result['density']['std_mean']:.3f} (mean over frames, h = {h:.4g} m)")
    # particles against ground truth
    gt_file = gt_path or (dataset.gt_file if dataset is not None else None)
    if gt_file:
        sim = read_sim(gt_file)
        spacing = 2.0 * sim.particle_radius
        rows = []
        for t in times:
            f = int(np.argmin(np.abs(sim.times - t)))
            if abs(sim.times[f] - t) > 0.5 / sim.fps + 1e-9:
                continue
            with torch.no_grad():
                p = model.at(float(t))["means"].cpu().numpy()
            rows.append({"time": float(t), "gt_frame": f, **particle_error(p, sim.positions[f], spacing)})
        if rows:
            result["particles_vs_gt"] = {
                "gt": str(gt_file), "spacing": spacing, "per_frame": rows,
                "gt_to_recon_mean": float(np.mean([x["gt_to_recon"] for x in rows])),
                "recon_to_gt_mean": float(np.mean([x["recon_to_gt"] for x in rows])),
                "gt_to_recon_max_frame": float(max(x["gt_to_recon"] for x in rows)),
                "recon_to_gt_max_frame": float(max(x["recon_to_gt"] for x in rows)),
                "gt_within_1_mean": float(np.mean([x["gt_to_recon_within_1"] for x in rows]))}
            pv = result["particles_vs_gt"]
            log(f"particles vs ground truth (spacing {spacing:.4g} m): true->recon {pv['gt_to_recon_mean']:.3f}, "
                f"recon->true {pv['recon_to_gt_mean']:.3f} spacings (worst frame {pv['gt_to_recon_max_frame']:.3f} / "
                f"{pv['recon_to_gt_max_frame']:.3f}); {100 * pv['gt_within_1_mean']:.1f}% of true particles covered")
    result["training"] = r.metrics
    metrics_file = (run if run.is_dir() else run.parent) / "metrics.jsonl"
    curve = read_metrics(metrics_file) if metrics_file.exists() else []
    out.mkdir(parents=True, exist_ok=True)
    result["plots"] = plot_eval(result, curve, out)
    atomic_write_text(out / "eval.json", json.dumps(result, indent=1))
    log(f"wrote {out / 'eval.json'} and {len(result['plots'])} plots")
    return result


def read_metrics(path: Path) -> list[dict]:
    rows = []
    with open(path) as f:
        for k, line in enumerate(f):
            line = line.strip()
            if not line:
                continue
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                raise InputError(path, f"line {k + 1} is not valid JSON") from None
    return rows


def plot_eval(result: dict, curve: list[dict], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []

    def save(fig, name):
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)

    if "train" in result or "test" in result:
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        for split in ("train", "test"):
            if split in result:
                pf = result[split]["per_frame"]
                ax[0].plot([p["time"] for p in pf], [p["psnr"] for p in pf], "o-", ms=3, label=split)
                ax[1].plot([p["time"] for p in pf], [p["ssim"] for p in pf], "o-", ms=3, label=split)
        ax[0].set(xlabel="time (s)", ylabel="PSNR (dB)", title="PSNR per frame")
        ax[1].set(xlabel="time (s)", ylabel="SSIM", title="SSIM per frame")
        ax[0].legend()
        save(fig, "eval_images.png")
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    d = result["density"]["per_frame"]
    ax.plot([x["time"] for x in d], [x["std"] for x in d], "o-", ms=3)
    ax.set(xlabel="time (s)", ylabel="std of D_i / mean D", title="SPH density spread (Fig. 4)")
    save(fig, "eval_density.png")
    if "particles_vs_gt" in result:
        pv = result["particles_vs_gt"]["per_frame"]
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        ax[0].plot([x["time"] for x in pv], [x["gt_to_recon"] for x in pv], "o-", ms=3, label="true -> recon")
        ax[0].plot([x["time"] for x in pv], [x["recon_to_gt"] for x in pv], "s-", ms=3, label="recon -> true")
        ax[0].axhline(1.0, color="gray", lw=0.8, ls="--")
        ax[0].set(xlabel="time (s)", ylabel="mean distance (true spacings)", title="particle error")
        ax[0].legend()
        ax[1].plot([x["time"] for x in pv], [x["particles_recon"] for x in pv], label="reconstructed")
        ax[1].plot([x["time"] for x in pv], [x["particles_gt"] for x in pv], label="true")
        ax[1].set(xlabel="time (s)", ylabel="particles", title="particle counts")
        ax[1].legend()
        save(fig, "eval_particles.png")
    if curve:
        fig, ax = plt.subplots(figsize=(5, 3.4))
        ax.plot([c["wall_s"] for c in curve], [c["train_psnr"] for c in curve], lw=1, label="training PSNR")
        te = [c for c in curve if "test_psnr" in c]
        if te:
            ax.plot([c["wall_s"] for c in te], [c["test_psnr"] for c in te], "o-", ms=3, label="held-out PSNR")
        for ph in (2, 3):
            first = next((c["wall_s"] for c in curve if c["phase"] == ph), None)
            if first is not None:
                ax.axvline(first, color="gray", lw=0.8, ls=":")
        ax.set(xlabel="wall-clock seconds", ylabel="PSNR (dB)", title="PSNR against run time")
        ax.legend()
        save(fig, "eval_psnr_vs_time.png")
    return files


__all__ = ["evaluate", "read_metrics", "plot_eval"]
