"""``gf-cli bench scenes``: the scene matrix -- does the reconstruction hold on scenes it was not tuned on?

Each scene of the suite (``gf_core/bench/scenes.toml``, or a file of the same shape) is made with
the project's own commands and judged the way a user would judge it:

1. ``gf-cli simulate`` (the scene's solver, particles, fps, seconds), ``gf-cli render-dataset``
   (its camera rig, resolution, samples, surface look, with or without a scene box);
2. ``gf-cli reconstruct`` with the default preset and the suite's time budget, for each seed;
3. ``gf-cli evaluate``: held-out PSNR/SSIM (mean and worst frame), training PSNR, both Chamfer
   directions in true spacings (mean and worst frame), interior coverage, the fraction of particles
   outside the true container, kinetic and total mechanical energy against the truth;
4. ``gf-cli bench reconstruct --per-frame`` at the same total time: every frame fitted on its own
   (3DGS, no time model), the simplest thing a user could do instead.

Every step is a batch job (``gf_core.batch``): its own ``gf-cli`` process (what a user runs,
nothing shared between steps but files), skipped when its output is already complete, so an
interrupted matrix resumes; ``gf-cli bench scenes --local N`` or ``--ray ADDRESS`` runs N at a
time here or on a Ray cluster. The
result is ``bench_scenes.json``, a table against the suite's targets, and a plot per scene of
the held-out PSNR and both Chamfer directions per frame beside the per-frame fit.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..formats.toml_file import read_toml

SUITE = Path(__file__).with_name("scenes.toml")
# the keys a scene may set (the suite's [defaults] gives every one a value)
SCENE_KEYS = ("scene", "solver", "particles", "fps", "seconds", "frames", "views", "test_views", "resolution",
              "samples", "denoise", "arc", "elevation", "test_elevation", "blob", "transmission", "scene_box",
              "time_format", "time_budget", "seeds", "preset", "target_overrides")
TARGET_KEYS = ("test_psnr_mean", "test_psnr_min", "test_ssim", "chamfer_mean", "chamfer_max", "outside_max",
               "kinetic_factor", "energy_rise")
# kinetic energy is compared where the truth has at least this share of its clip maximum (a fluid at
# rest has a kinetic energy of about 0, where a factor means nothing)
KINETIC_FLOOR = 0.05


def load_suite(path: Path | None = None, *, quick: bool = False, only: list[str] | None = None) -> dict:
    """{"scenes": {name: spec}, "targets": {...}} with every scene's keys filled from [defaults]
    (and [quick] with ``quick``). Unknown keys, scenes and bad values are errors naming the file."""
    path = Path(path or SUITE)
    data = read_toml(path, "suite file")
    for sec in data:
        if sec not in ("defaults", "quick", "scenes", "targets"):
            raise InputError(path, f"unknown section [{sec}] (known: defaults, quick, scenes, targets)")
    defaults = data.get("defaults", {})
    for k in SCENE_KEYS:
        if k not in defaults and k not in ("scene", "target_overrides"):
            raise InputError(path, f"[defaults] lacks {k!r}")
    targets = data.get("targets", {})
    for k in TARGET_KEYS:
        if not isinstance(targets.get(k), (int, float)) or isinstance(targets.get(k), bool):
            raise InputError(path, f"[targets] {k} must be a number")
    scenes = {}
    for name, sc in (data.get("scenes") or {}).items():
        for k in list(sc) + list(data.get("quick", {})) + list(defaults):
            if k not in SCENE_KEYS:
                raise InputError(path, f"scene {name}: unknown key {k!r} (known: {', '.join(SCENE_KEYS)})")
        if "scene" not in sc:
            raise InputError(path, f"scene {name}: needs 'scene' (a gf-cli simulate scene)")
        spec = {**defaults, **sc, **(data.get("quick", {}) if quick else {})}
        for k in spec.get("target_overrides", {}):
            if k not in TARGET_KEYS:
                raise InputError(path, f"scene {name}: unknown target {k!r} (known: {', '.join(TARGET_KEYS)})")
        if not isinstance(spec["seeds"], list) or not spec["seeds"] or \
                any(isinstance(s, bool) or not isinstance(s, int) for s in spec["seeds"]):
            raise InputError(path, f"scene {name}: seeds must be a list of integers, got {spec['seeds']!r}")
        if not spec["time_budget"] > 0:
            raise InputError(path, f"scene {name}: time_budget must be positive seconds, got {spec['time_budget']!r}")
        scenes[name] = spec
    if not scenes:
        raise InputError(path, "has no [scenes.NAME] table")
    if only:
        unknown = [n for n in only if n not in scenes]
        if unknown:
            raise InputError("--only", f"unknown scene(s) {', '.join(unknown)}; the suite has {', '.join(scenes)}")
        scenes = {n: scenes[n] for n in only}
    return {"scenes": scenes, "targets": targets, "path": str(path), "quick": quick}


def scene_jobs(suite: dict, *, seeds: list[int] | None = None, per_frame: bool = True,
               cpus: float = 2.0) -> dict:
    """The matrix as batch jobs ({name: spec}, ``gf_core.batch.expand``'s form): per scene
    ``NAME/sim``, ``NAME/dataset``, ``NAME/per_frame`` and, per seed, ``NAME/recon_seedS`` and
    ``NAME/eval_seedS``; ``cpus`` threads for each reconstruction and per-frame fit."""
    from ..recon.config import make_config

    jobs = {}
    for name, spec in suite["scenes"].items():
        jobs[f"{name}/sim"] = {"run": ["simulate", spec["scene"], "--solver", spec["solver"], "--particles",
                                       spec["particles"], "--fps", spec["fps"], "--seconds", spec["seconds"],
                                       "--out", "{dir}/sim.h5", "--quiet"], "outputs": ["sim.h5"]}
        args = ["render-dataset", f"{{{name}/sim}}/sim.h5", "--out", "{dir}", "--views", spec["views"],
                "--test-views", spec["test_views"], "--resolution", spec["resolution"], "--samples", spec["samples"],
                "--frames", spec["frames"], "--arc", spec["arc"], "--elevation", spec["elevation"],
                "--test-elevation", spec["test_elevation"], "--blob", spec["blob"], "--time-format", spec["time_format"]]
        if spec["transmission"] >= 0:
            args += ["--transmission", spec["transmission"]]
        if spec["denoise"]:
            args.append("--denoise")
        if not spec["scene_box"]:
            args.append("--no-scene-box")
        jobs[f"{name}/dataset"] = {"run": args, "outputs": ["transforms_train.json"]}
        ds = f"{{{name}/dataset}}"
        if per_frame:
            n = make_config(spec["preset"]).model.max_particles
            jobs[f"{name}/per_frame"] = {
                "run": ["bench", "reconstruct", ds, "--per-frame", "--preset", spec["preset"], "--iterations",
                        1_000_000, "--particles", n, "--time-budget", spec["time_budget"], "--out", "{dir}"],
                "outputs": ["bench_reconstruct.json"], "num_cpus": cpus}
        for seed in (seeds or spec["seeds"]):
            jobs[f"{name}/recon_seed{seed}"] = {
                "run": ["reconstruct", ds, "--out", "{dir}", "--preset", spec["preset"], "--time-budget",
                        spec["time_budget"], "--seed", seed, "--quiet"], "outputs": ["recon.h5"], "num_cpus": cpus}
            jobs[f"{name}/eval_seed{seed}"] = {
                "run": ["evaluate", f"{{{name}/recon_seed{seed}}}", "--dataset", ds, "--out", "{dir}"],
                "outputs": ["eval.json"], "num_cpus": cpus}
    for spec in jobs.values():
        spec["run"] = [str(a) for a in spec["run"]]
    return jobs


def scene_record(name: str, spec: dict, ev: dict, pf: dict | None, targets: dict) -> dict:
    """The matrix row of one reconstruction: figures, per-frame series, and which targets it meets."""
    te, tr = ev.get("test", {}), ev.get("train", {})
    rec = {"scene": name, "kind": spec["scene"], "particles_true": None,
           "test_psnr_mean": te.get("psnr_mean"), "test_psnr_min": te.get("psnr_min_frame"),
           "test_ssim": te.get("ssim_mean"), "train_psnr_mean": tr.get("psnr_mean"),
           "iterations": ev["training"].get("iterations"), "wall_s": ev["training"].get("wall_s"),
           "particles": ev.get("particles"), "phase_ends": ev["training"].get("phase_ends")}
    pv = ev.get("particles_vs_gt")
    series = {"time": [f["time"] for f in te.get("per_frame", [])],
              "test_psnr": [f["psnr"] for f in te.get("per_frame", [])]}
    if pv:
        rows = pv["per_frame"]
        rec.update(particles_true=rows[0]["particles_gt"], gt_to_recon_mean=pv["gt_to_recon_mean"],
                   recon_to_gt_mean=pv["recon_to_gt_mean"], gt_to_recon_max=pv["gt_to_recon_max_frame"],
                   recon_to_gt_max=pv["recon_to_gt_max_frame"], coverage=pv["gt_within_1_mean"],
                   outside_max=pv["outside_container_max_frame"], flow_following=pv.get("flow_following_mean"))
        series.update(chamfer_time=[r["time"] for r in rows], gt_to_recon=[r["gt_to_recon"] for r in rows],
                      recon_to_gt=[r["recon_to_gt"] for r in rows])
    en = ev.get("energy", {}).get("per_frame", [])
    if en and "gt_kinetic" in en[0]:
        kmax = max(r["gt_kinetic"] for r in en)
        ratios = [max(r["kinetic"], 1e-30) / r["gt_kinetic"] for r in en
                  if kmax > 0 and r["gt_kinetic"] >= KINETIC_FLOOR * kmax]
        rec["kinetic_factor_max"] = float(max(max(q, 1 / q) for q in ratios)) if ratios else math.nan
        # the same factor on the kinetic energy per kilogram (the mean squared speed), and the mass
        # estimate's ratio to the truth's: the kinetic factor is their product
        if "gt_speed_rms" in en[0]:
            per_kg = [(max(r["speed_rms"], 1e-15) / r["gt_speed_rms"]) ** 2 for r in en
                      if kmax > 0 and r["gt_kinetic"] >= KINETIC_FLOOR * kmax]
            rec["specific_kinetic_factor_max"] = float(max(max(q, 1 / q) for q in per_kg)) if per_kg else math.nan
            rec["mass_ratio"] = float(ev["energy"]["mass_total"] / ev["energy"]["gt_mass_total"])
        e0 = en[0]["total"]
        rec["energy_rise_max"] = float(max(r["total"] - e0 for r in en) / abs(e0)) if e0 else math.nan
        series.update(energy_time=[r["time"] for r in en], kinetic=[r["kinetic"] for r in en],
                      gt_kinetic=[r["gt_kinetic"] for r in en], total=[r["total"] for r in en],
                      gt_total=[r["gt_total"] for r in en])
    if pf is not None:
        frames = sorted(pf["records"], key=lambda r: r["time"])
        pf_psnr = [r["test_psnr"] for r in frames]
        rec["per_frame_test_psnr_mean"] = float(np.mean(pf_psnr)) if pf_psnr and None not in pf_psnr else None
        rec["per_frame_test_psnr_min"] = float(np.min(pf_psnr)) if pf_psnr and None not in pf_psnr else None
        rec["per_frame_wall_s"] = float(sum(r["wall_s"] for r in frames))
        if frames and "gt_to_recon" in frames[0]:
            rec["per_frame_gt_to_recon_mean"] = float(np.mean([r["gt_to_recon"] for r in frames]))
            rec["per_frame_recon_to_gt_mean"] = float(np.mean([r["recon_to_gt"] for r in frames]))
        series.update(per_frame_time=[r["time"] for r in frames], per_frame_test_psnr=pf_psnr)
        # frames where the time-continuous reconstruction is below the per-frame fit (held-out PSNR)
        ours = dict(zip(np.round(series["time"], 6), series["test_psnr"]))
        below = [t for t, p in zip(np.round(series["per_frame_time"], 6), pf_psnr)
                 if p is not None and t in ours and ours[t] < p]
        rec["frames_below_per_frame"] = len(below)
    rec["series"] = series
    rec["targets"] = judge(rec, {**targets, **spec.get("target_overrides", {})})
    return rec


def judge(rec: dict, t: dict) -> dict:
    """{target: True/False/None (not measurable here)} for one row."""
    def at_least(v, x):
        return None if v is None or not np.isfinite(v) else bool(v >= x)

    def at_most(v, x):
        return None if v is None or not np.isfinite(v) else bool(v <= x)

    out = {"test_psnr_mean": at_least(rec.get("test_psnr_mean"), t["test_psnr_mean"]),
           "test_psnr_min": at_least(rec.get("test_psnr_min"), t["test_psnr_min"]),
           "test_ssim": at_least(rec.get("test_ssim"), t["test_ssim"])}
    if "gt_to_recon_mean" in rec:
        out["chamfer_mean"] = bool(max(rec["gt_to_recon_mean"], rec["recon_to_gt_mean"]) <= t["chamfer_mean"])
        out["chamfer_max"] = bool(max(rec["gt_to_recon_max"], rec["recon_to_gt_max"]) <= t["chamfer_max"])
        out["outside_max"] = at_most(rec["outside_max"], t["outside_max"])
    if "kinetic_factor_max" in rec:
        out["kinetic_factor"] = at_most(rec["kinetic_factor_max"], t["kinetic_factor"])
        out["energy_rise"] = at_most(rec["energy_rise_max"], t["energy_rise"])
    if "frames_below_per_frame" in rec:
        out["not_below_per_frame"] = rec["frames_below_per_frame"] == 0
    return out


def bench_scenes(work: Path, suite: dict, *, seeds: list[int] | None = None, per_frame: bool = True,
                 executor=None, cpus: float = 2.0, log=print) -> list[dict]:
    """Every scene of ``suite`` (``load_suite``) made, reconstructed per seed, evaluated and set
    beside its per-frame fit, as batch jobs on ``executor`` (default: one at a time here); jobs
    already complete are skipped. One record per (scene, seed) whose jobs all finished."""
    from ..batch import LocalExecutor, expand, run_jobs

    work = Path(work)
    jobs = expand(scene_jobs(suite, seeds=seeds, per_frame=per_frame, cpus=cpus), work, suite["path"],
                  default_retries=0)
    states = {r["job"]: r["state"] for r in run_jobs(jobs, work, executor or LocalExecutor(1), log=log)}
    ok = {n for n, st in states.items() if st.startswith("done")}
    records = []
    for name, spec in suite["scenes"].items():
        pf = json.loads((work / name / "per_frame" / "bench_reconstruct.json").read_text()) \
            if per_frame and f"{name}/per_frame" in ok else None
        for seed in (seeds or spec["seeds"]):
            if f"{name}/eval_seed{seed}" not in ok:
                log(f"  {name} seed {seed}: not evaluated (a job it needs did not finish: see the batch summary)")
                continue
            ev = json.loads((work / name / f"eval_seed{seed}" / "eval.json").read_text())
            rec = scene_record(name, spec, ev, pf, suite["targets"])
            rec["seed"] = seed
            records.append(rec)
            log(f"  {name} seed {seed}: held-out {_f(rec['test_psnr_mean'])} dB (worst {_f(rec['test_psnr_min'])}), "
                f"true->recon {_f(rec.get('gt_to_recon_mean'), 3)}, recon->true {_f(rec.get('recon_to_gt_mean'), 3)}, "
                f"targets missed: {', '.join(k for k, v in rec['targets'].items() if v is False) or 'none'}")
    return records


def _f(v, nd: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


COLUMNS = [("scene", "scene", "s"), ("seed", "seed", "d"), ("particles_true", "N true", "d"),
           ("iterations", "it", "d"), ("wall_s", "wall s", ".0f"), ("train_psnr_mean", "train dB", ".2f"),
           ("test_psnr_mean", "held-out dB", ".2f"), ("test_psnr_min", "worst", ".2f"), ("test_ssim", "SSIM", ".3f"),
           ("per_frame_test_psnr_mean", "3DGS/frame dB", ".2f"), ("per_frame_test_psnr_min", "3DGS worst", ".2f"),
           ("gt_to_recon_mean", "t->r", ".2f"), ("gt_to_recon_max", "t->r max", ".2f"),
           ("recon_to_gt_mean", "r->t", ".2f"), ("recon_to_gt_max", "r->t max", ".2f"),
           ("coverage", "covered", ".2f"), ("outside_max", "outside", ".3f"),
           ("kinetic_factor_max", "KE factor", ".2f"), ("specific_kinetic_factor_max", "KE/kg factor", ".2f"),
           ("mass_ratio", "mass", ".2f"), ("flow_following", "flow", ".2f"),
           ("energy_rise_max", "E rise", "+.2f"), ("missed", "missed", "s")]


def table_rows(records: list[dict]) -> list[dict]:
    return [{**r, "missed": ",".join(k for k, v in r["targets"].items() if v is False) or "-"} for r in records]


def plot_scenes(records: list[dict], out: Path) -> list[str]:
    """One PNG per scene: held-out PSNR per frame (ours per seed, the per-frame fit), both Chamfer
    directions per frame, kinetic energy against the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for name in dict.fromkeys(r["scene"] for r in records):
        rs = [r for r in records if r["scene"] == name]
        fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
        for r in rs:
            s = r["series"]
            ax[0].plot(s["time"], s["test_psnr"], "o-", ms=3, label=f"GaussFluids, seed {r['seed']}")
            if "gt_to_recon" in s:
                ax[1].plot(s["chamfer_time"], s["gt_to_recon"], "-", label=f"true->recon, seed {r['seed']}")
                ax[1].plot(s["chamfer_time"], s["recon_to_gt"], "--", label=f"recon->true, seed {r['seed']}")
            if "kinetic" in s:
                ax[2].plot(s["energy_time"], s["kinetic"], "-", label=f"reconstruction, seed {r['seed']}")
        s = rs[0]["series"]
        if "per_frame_test_psnr" in s:
            ax[0].plot(s["per_frame_time"], s["per_frame_test_psnr"], "k^--", ms=3, lw=0.8, label="per-frame 3DGS fit")
        if "gt_kinetic" in s:
            ax[2].plot(s["energy_time"], s["gt_kinetic"], "k-", lw=1.5, label="truth")
        ax[0].set(xlabel="time (s)", ylabel="held-out PSNR (dB)", title=f"{name}: held-out view")
        ax[1].set(xlabel="time (s)", ylabel="true particle spacings", title="Chamfer, both directions")
        ax[2].set(xlabel="time (s)", ylabel="kinetic energy (J)", title="kinetic energy (decoder velocities)")
        for a in ax:
            a.legend(fontsize=7)
        fig.tight_layout()
        p = Path(out) / f"scene_{name}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(str(p))
    return paths


__all__ = ["load_suite", "bench_scenes", "scene_record", "judge", "plot_scenes", "table_rows", "COLUMNS", "SUITE"]
