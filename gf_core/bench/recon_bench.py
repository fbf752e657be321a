"""``gf-cli bench reconstruct DATASET``: error against run time for the whole method.

A grid of iteration budgets x particle budgets is reconstructed on one dataset; each run is
evaluated on the held-out views (PSNR/SSIM) and, when the dataset carries its particles, against
them (both Chamfer directions, in true spacings), next to its wall-clock seconds. The plot shows
every run as a point (held-out PSNR and Chamfer against seconds, the Pareto front joined) and
each run's held-out PSNR trace from its ``metrics.jsonl``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def pareto(points: list[tuple[float, float]], higher_is_better: bool) -> list[int]:
    """Indices of the points no other point beats in both cost (lower) and value."""
    sign = 1.0 if higher_is_better else -1.0
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -sign * points[i][1]))
    front, best = [], -np.inf
    for i in order:
        v = sign * points[i][1]
        if v > best:
            front.append(i)
            best = v
    return front


def bench_reconstruct(dataset: Path, out: Path, *, iterations: list[int], particles: list[int], preset: str = "water",
                      config_file=None, device: str = "cpu", frames: slice | None = None, per_frame: bool = False,
                      time_budget: float = 0.0, seed: int | None = None, load_options: dict | None = None,
                      log=print) -> list[dict]:
    """One record per run. With ``per_frame``, every selected frame is fitted on its own (a static
    scene: no decoder, no time model) for every budget pair: the per-frame reference that a
    time-continuous reconstruction of the same images is measured against. ``time_budget`` (s,
    > 0): each run stops at it instead of at its iterations; per frame, the frames share it
    equally (the same total time as one reconstruction of the clip). ``load_options``: how the
    images are read (``load_dataset``'s grayscale, background_removal, resolution, downscale)."""
    from ..data import has_split, load_dataset
    from ..eval.evaluate import evaluate, read_metrics
    from ..recon.config import make_config
    from ..recon.trainer import reconstruct

    def quiet(*a, **k):
        pass

    train = load_dataset(dataset, **(load_options or {}))
    test = None
    if has_split(dataset, "test"):
        test = load_dataset(dataset, split="test", **(load_options or {}))
    if frames is not None:
        train = train.select_times(frames)
        test = test.with_times(train.times) if test is not None else None
    records = []
    frame_times = [float(t) for t in np.unique(train.times)] if per_frame else [None]

    def clips():  # one frame's images at a time: a clip's pixels are dropped once it is fitted
        for t in frame_times:
            yield (t, train, test) if t is None else \
                (t, train.with_times([t]), None if test is None else test.with_times([t]))
    for n in particles:
        for it in iterations:
            for t, tr_ds, te_ds in clips():
                base = make_config(preset, config_file)
                over = {"phases": {"iterations": it, "limit_factor": 1.0},  # the budget swept, exactly
                        "model": {"max_particles": n, "init_particles": min(n, base.model.init_particles)}}
                if time_budget > 0:
                    over["train"] = {"time_budget_s": float(time_budget) / len(frame_times)}
                if seed is not None:
                    over.setdefault("train", {})["seed"] = int(seed)
                cfg = make_config(preset, config_file, over)
                run = out / (f"run_it{it}_n{n}" + ("" if t is None else f"_t{t:.4f}"))
                for stale in ("recon.h5", "checkpoint.pt", "metrics.jsonl"):
                    (run / stale).unlink(missing_ok=True)
                m = reconstruct(tr_ds, run, cfg, test_dataset=te_ds, device=device, log=quiet)
                ev = evaluate(run, dataset=tr_ds, test_dataset=te_ds, device=device, log=quiet)
                rec = {"iterations_budget": it, "particle_budget": n, "iterations": m["iterations"],
                       "particles": m["particles"], "wall_s": m["wall_s"],
                       "train_psnr": ev["train"]["psnr_mean"],
                       "test_psnr": ev["test"]["psnr_mean"] if "test" in ev else None,
                       "test_psnr_min_frame": ev["test"]["psnr_min_frame"] if "test" in ev else None,
                       "test_ssim": ev["test"]["ssim_mean"] if "test" in ev else None,
                       "density_std": ev["density"]["std_mean"]}
                if "particles_vs_gt" in ev:
                    pv = ev["particles_vs_gt"]
                    rec.update(gt_to_recon=pv["gt_to_recon_mean"], recon_to_gt=pv["recon_to_gt_mean"],
                               chamfer=0.5 * (pv["gt_to_recon_mean"] + pv["recon_to_gt_mean"]))
                if ev.get("density_vs_gt", {}).get("corr_mean") is not None:   # a smoke dataset's true grid
                    rec.update(density_corr=ev["density_vs_gt"]["corr_mean"],
                               density_corr_min_frame=ev["density_vs_gt"]["corr_min_frame"])
                curve = read_metrics(run / "metrics.jsonl")
                rec["trace"] = [{"wall_s": c["wall_s"], "test_psnr": c["test_psnr"]} for c in curve if "test_psnr" in c]
                if t is not None:
                    rec["time"] = t
                records.append(rec)
                log(("" if t is None else f"frame at {t:.4f} s: ") + f"iterations {it:>6} particles {n:>6}: "
                    f"{m['wall_s']:7.1f} s, held-out PSNR "
                    f"{rec['test_psnr'] if rec['test_psnr'] is not None else float('nan'):.2f} dB"
                    + (f", Chamfer {rec['gt_to_recon']:.3f} / {rec['recon_to_gt']:.3f} spacings" if "chamfer" in rec else ""))
    return records


def plot_per_frame(records: list[dict], path: Path) -> None:
    """Held-out (else training) PSNR of the per-frame fits against the frame's time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = "test_psnr" if all(r["test_psnr"] is not None for r in records) else "train_psnr"
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for n in sorted({r["particle_budget"] for r in records}):
        for it in sorted({r["iterations_budget"] for r in records}):
            rs = sorted((r for r in records if r["particle_budget"] == n and r["iterations_budget"] == it),
                        key=lambda r: r["time"])
            ax.plot([r["time"] for r in rs], [r[key] for r in rs], "o-", label=f"{it} it, {n} particles at most")
    ax.set(xlabel="frame time (s)", ylabel=("held-out" if key == "test_psnr" else "training") + " PSNR (dB)",
           title="each frame fitted on its own (no time model)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    psnr_key = "test_psnr" if all(r["test_psnr"] is not None for r in records) else "train_psnr"
    panels = [(psnr_key, "held-out PSNR (dB)" if psnr_key == "test_psnr" else "training PSNR (dB)", True)]
    if all("chamfer" in r for r in records):
        panels.append(("chamfer", "Chamfer, mean of both directions (spacings)", False))
    fig, ax = plt.subplots(1, len(panels) + 1, figsize=(5 * (len(panels) + 1), 3.8))
    for k, (key, label, higher) in enumerate(panels):
        pts = [(r["wall_s"], r[key]) for r in records]
        for n in sorted({r["particle_budget"] for r in records}):
            rs = [r for r in records if r["particle_budget"] == n]
            ax[k].plot([r["wall_s"] for r in rs], [r[key] for r in rs], "o", label=f"{n} particles at most")
        front = pareto(pts, higher)
        ax[k].plot([pts[i][0] for i in front], [pts[i][1] for i in front], "k--", lw=0.8, label="Pareto front")
        for r in records:
            ax[k].annotate(f"{r['iterations_budget']} it", (r["wall_s"], r[key]), fontsize=7)
        ax[k].set(xlabel="wall-clock seconds", ylabel=label, title=label.split(" (")[0] + " vs run time")
        ax[k].legend(fontsize=7)
    for r in records:
        tr = r["trace"]
        if tr:
            ax[-1].plot([t["wall_s"] for t in tr], [t["test_psnr"] for t in tr], lw=1,
                        label=f"{r['iterations_budget']} it, {r['particle_budget']} p")
    ax[-1].set(xlabel="wall-clock seconds", ylabel="held-out PSNR during training (dB)", title="training traces")
    ax[-1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["bench_reconstruct", "plot", "plot_per_frame", "pareto"]
