"""``gf-cli evaluate``: judge a reconstruction by what the images, the physics and (when known)
the true particles say, per split, view and frame; writes ``eval.json`` and PNG plots.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..formats.hdf5 import atomic_write_text, read_recon, read_sim
from ..recon.model import FluidModel
from ..recon.views import composited
from ..render import render
from .metrics import density_spread, flow_error, image_metrics, mechanical_energy, particle_error, shape_spread, \
    transport_distance


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
        target = composited(ds, i, bg)
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


def _density_vs_grid(path: Path, times, states, log) -> dict:
    """The reconstruction's density (its Gaussians averaged over each of the grid's cells) against
    the true density grid (a smoke dataset's ``gt_density``), at the frames both have."""
    from ..formats.hdf5 import read_grid
    from .metrics import density_agreement, gaussian_cell_mean

    g = read_grid(path)
    recon, truth, used = [], [], []
    for t, st in zip(times, states):
        f = int(np.argmin(np.abs(g.times - t)))
        if abs(g.times[f] - t) > 0.5 / g.fps + 1e-9:
            continue
        recon.append(gaussian_cell_mean(*(st[k].detach().cpu().numpy() for k in ("means", "scales", "quats")),
                                        st["opacities"].detach().reshape(-1).cpu().numpy(), g.domain_min, g.cell,
                                        g.density.shape[1:]))
        truth.append(g.density[f].reshape(-1))
        used.append(float(t))
    if not used:
        raise InputError(path, "none of its frames is at a frame time of the reconstruction")
    res = density_agreement(recon, truth)
    for row, t in zip(res["per_frame"], used):
        row["time"] = t
    res.update(gt=str(path), grid=list(g.density.shape[1:]), sampling="cell means")
    scored = sum(r["corr"] is not None for r in res["per_frame"])
    if scored:
        log(f"density vs the true grid ({'x'.join(map(str, g.density.shape[1:]))} cells, {scored} frames with "
            f"smoke of {len(used)}): correlation {res['corr_mean']:.3f} (worst frame {res['corr_min_frame']:.3f}), "
            f"relative error {res['error_mean']:.3f}")
    else:
        log(f"density vs the true grid: no smoke in its {len(used)} frames at the reconstruction's times")
    return res


def evaluate(run: Path, *, dataset=None, test_dataset=None, gt_path=None, device="cpu", out: Path | None = None,
             rest_density: float | None = None, upsample: int | None = None, log=print) -> dict:
    run = Path(run)
    recon_path = run / "recon.h5" if run.is_dir() else run
    out = Path(out) if out else (run if run.is_dir() else run.parent)
    out.mkdir(parents=True, exist_ok=True)
    r = read_recon(recon_path)
    model = FluidModel.from_recon(r, device=device)
    result = {"recon": str(recon_path), "particles": len(model), "dynamic": model.is_dynamic}
    if model.is_dynamic and dataset is not None and len(dataset):  # frames outside the clip were never fitted (predict goes there)
        inside = [t for t in dataset.times if r.time_min - 1e-6 <= t <= r.time_max + 1e-6]
        if not inside:
            raise InputError(dataset.root, "none of its frame times lies inside the reconstructed clip "
                                           f"[{r.time_min:g}, {r.time_max:g}] s")
        if len(inside) < len(dataset.times):
            log(f"evaluating the {len(inside)} of {len(dataset.times)} frame times inside the reconstructed clip "
                f"[{r.time_min:g}, {r.time_max:g}] s")
            dataset = dataset.with_times(inside)
            test_dataset = test_dataset.with_times(inside) if test_dataset is not None else None
    if dataset is not None:
        for name, ds in (("train", dataset), ("test", test_dataset)):
            if ds is None or len(ds) == 0:
                continue
            if ds.channels != model.channels:
                raise InputError(ds.root, f"{ds.channels}-channel images for a {model.channels}-channel reconstruction")
            result[name] = _summary(_render_split(model, ds, device))
            log(f"{name}: PSNR {result[name]['psnr_mean']:.2f} dB, SSIM {result[name]['ssim_mean']:.3f} "
                f"over {len(ds)} images (worst frame {result[name]['psnr_min_frame']:.2f} dB)")
    if upsample:
        if dataset is None:
            raise InputError("--upsample", "needs the dataset (the training views and the frames held out in time)")
        from .resample import upsample as resample

        result["upsample"] = resample(model, r, dataset, upsample, out=out, device=device, log=log)
    # physics: the SPH density spread per frame
    times = np.unique([f.time for f in dataset.frames]) if dataset is not None else \
        np.linspace(model.time_map.t_min, model.time_map.t_max, 10 if model.is_dynamic else 1)
    h = float(r.config.get("h") or 2.5 * (r.config.get("spacing") or 1.0))
    with torch.no_grad():  # decoded once per time: positions and velocities for every figure below
        states = [model.at(float(t), with_velocity=True) for t in times]
    dens = [{"time": float(t), **density_spread(st["means"], h)} for t, st in zip(times, states)]
    result["density"] = {"h": h, "per_frame": dens, "std_mean": float(np.mean([d["std"] for d in dens]))}
    log(f"SPH density D_i / mean: standard deviation {result['density']['std_mean']:.3f} (mean over frames, h = {h:.4g} m)")
    shp = [{"time": float(t), **shape_spread(st["scales"])} for t, st in zip(times, states)]
    result["shape"] = {"per_frame": shp, **{f"{k}_mean": float(np.mean([f[k] for f in shp]))
                                            for k in ("volume", "aniso", "axis_ratio_median", "axis_ratio_p95")}}
    log(f"particle shapes: L_vol {result['shape']['volume_mean']:.3f}, L_aniso {result['shape']['aniso_mean']:.3f}, "
        f"longest/shortest axis median {result['shape']['axis_ratio_median_mean']:.2f}, 95th percentile "
        f"{result['shape']['axis_ratio_p95_mean']:.2f} (means over frames)")
    result["particle_stats"] = particle_stats(r)
    gt_file = gt_path or (dataset.gt_file if dataset is not None else None)
    sim = read_sim(gt_file) if gt_file else None
    result["energy"] = energies(model, r, times, states, sim, rest_density)
    e = result["energy"]
    log(f"mechanical energy (mass {e['mass_per_particle']:.3g} kg per particle, {e['mass_source']}): "
        f"total {e['per_frame'][0]['total']:.4g} J at t = {times[0]:.3g} s -> {e['per_frame'][-1]['total']:.4g} J "
        f"at t = {times[-1]:.3g} s")
    # particles against ground truth
    if sim is not None:
        spacing = 2.0 * sim.particle_radius
        rows = []
        for t, st in zip(times, states):
            f = int(np.argmin(np.abs(sim.times - t)))
            if abs(sim.times[f] - t) > 0.5 / sim.fps + 1e-9:
                continue
            p = st["means"].cpu().numpy()
            # the true container: a reconstructed centre beyond its walls is fluid where none can be
            outside = float(np.any((p < np.asarray(sim.domain_min)) | (p > np.asarray(sim.domain_max)), 1).mean()) \
                if len(p) else 0.0
            rows.append({"time": float(t), "gt_frame": f, **particle_error(p, sim.positions[f], spacing),
                         **transport_distance(p, sim.positions[f], spacing), "outside_container": outside,
                         **flow_error(p, st["velocities"].cpu().numpy(), sim.positions[f], sim.velocities[f])})
        if rows:
            result["particles_vs_gt"] = {
                "gt": str(gt_file), "spacing": spacing, "per_frame": rows,
                "gt_to_recon_mean": float(np.mean([x["gt_to_recon"] for x in rows])),
                "recon_to_gt_mean": float(np.mean([x["recon_to_gt"] for x in rows])),
                "gt_to_recon_max_frame": float(max(x["gt_to_recon"] for x in rows)),
                "recon_to_gt_max_frame": float(max(x["recon_to_gt"] for x in rows)),
                "gt_within_1_mean": float(np.mean([x["gt_to_recon_within_1"] for x in rows])),
                "outside_container_max_frame": float(max(x["outside_container"] for x in rows)),
                "emd_mean": float(np.mean([x["emd"] for x in rows])),
                # the flow at the reconstructed particles, over the frames where the true fluid moves
                # (root mean square speed there above 10 % of the clip's largest)
                **_flow_summary(rows),
                "emd_solver": "exact assignment (scipy linear_sum_assignment) of equal random subsamples of "
                              f"at most {rows[0]['emd_samples']} particles",
                # what subsampling alone gives: two disjoint random halves of the true particles
                "emd_floor": _emd_floor(sim.positions[rows[0]["gt_frame"]], spacing)}
            pv = result["particles_vs_gt"]
            log(f"particles vs ground truth (spacing {spacing:.4g} m): true->recon {pv['gt_to_recon_mean']:.3f}, "
                f"recon->true {pv['recon_to_gt_mean']:.3f} spacings (worst frame {pv['gt_to_recon_max_frame']:.3f} / "
                f"{pv['recon_to_gt_max_frame']:.3f}); {100 * pv['gt_within_1_mean']:.1f}% of true particles covered; "
                f"at most {100 * pv['outside_container_max_frame']:.1f}% of the particles outside the true container; "
                f"earth mover's distance {pv['emd_mean']:.3f} spacings (subsampling floor {pv['emd_floor']:.3f})")
            if math.isfinite(pv["flow_following_mean"]):
                log(f"flow at the reconstructed particles (the nearest true particle's velocity): they follow "
                    f"{pv['flow_following_mean']:.2f} of it (worst frame {pv['flow_following_min_frame']:.2f}; 1 = "
                    f"with the flow, 0 = standing still), mean velocity error {pv['velocity_error_mean']:.3f} m/s")
    if dataset is not None and dataset.meta.get("gt_density"):
        result["density_vs_gt"] = _density_vs_grid(Path(dataset.meta["gt_density"]), times, states, log)
    result["training"] = r.metrics
    metrics_file = (run if run.is_dir() else run.parent) / "metrics.jsonl"
    curve = read_metrics(metrics_file) if metrics_file.exists() else []
    out.mkdir(parents=True, exist_ok=True)
    result["plots"] = plot_eval(result, curve, out)
    atomic_write_text(out / "eval.json", json.dumps(result, indent=1))
    log(f"wrote {out / 'eval.json'} and {len(result['plots'])} plots")
    return result


def continuation_appearance(sim, where, device="cpu"):
    """(model, look) for rendering a continuation (``sim``, a SimData from predict/edit): the
    reconstruction it names, and per simulated particle the scale, rotation, opacity and SH of its
    source Gaussian at the start time."""
    recon = sim.config.get("recon")
    if sim.source_index is None or not recon:
        raise InputError(where, "is not a continuation of a reconstruction (no source_index / recon in it): "
                                "evaluate takes a run folder, a recon.h5, or a sim.h5 from gf-cli predict/edit")
    if not Path(recon).exists():
        raise InputError(where, f"names the reconstruction {recon}, which does not exist any more")
    r = read_recon(recon)
    if sim.source_index.max(initial=-1) >= r.num_particles:
        raise InputError(where, f"source_index reaches {int(sim.source_index.max())} but {recon} has "
                                f"{r.num_particles} particles")
    model = FluidModel.from_recon(r, device=device)
    with torch.no_grad():
        app = model.at(float(sim.config.get("start_time_s", sim.times[0])))
    idx = torch.as_tensor(sim.source_index, device=device)
    return model, {k: app[k][idx] for k in ("scales", "quats", "opacities", "sh")}


def evaluate_continuation(sim_path: Path, *, dataset=None, test_dataset=None, gt_path=None, device="cpu",
                          out: Path | None = None, log=print) -> dict:
    """Judge a prediction or edit (``gf-cli predict``/``edit``): render every frame of the
    ``sim.h5`` with the learned appearance (each particle keeps the scale, rotation, opacity and
    colour its source Gaussian had at the start time) into the dataset's views at the same times
    and compare with the images (PSNR/SSIM, paper Table 8); compare the particles with the ground
    truth's at the same times (both Chamfer directions, in true spacings). Writes
    ``<stem>_eval.json`` and ``<stem>_eval.png`` beside the sim.h5 (or in ``out``)."""
    sim_path = Path(sim_path)
    sim = read_sim(sim_path)
    model, look = continuation_appearance(sim, sim_path, device)
    recon, t0 = sim.config["recon"], float(sim.config.get("start_time_s", sim.times[0]))
    tol = 0.5 / sim.fps + 1e-9
    result = {"sim": str(sim_path), "recon": recon, "start_time_s": t0, "particles": sim.num_particles,
              "frames": sim.num_frames, "edits": sim.config.get("edits", [])}
    for name, ds in (("train", dataset), ("test", test_dataset)):
        if ds is None or len(ds) == 0:
            continue
        bg = torch.as_tensor(np.asarray(ds.background, np.float64)[:ds.channels], dtype=torch.float32, device=device)
        rows = []
        for i, rec in enumerate(ds.frames):
            f = int(np.argmin(np.abs(sim.times - rec.time)))
            if abs(sim.times[f] - rec.time) > tol or f == 0:
                continue  # frame 0 is the reconstruction itself, not a prediction
            target = composited(ds, i, bg)
            with torch.no_grad():
                o = render(torch.as_tensor(sim.positions[f], device=device), look["scales"], look["quats"],
                           look["opacities"], look["sh"], rec.camera, bg, sh_degree=model.sh_degree)
            rows.append({"view": rec.view_id, "time": rec.time, "frame": f, **image_metrics(o.color, target)})
        if rows:
            result[name] = _summary(rows)
            log(f"{name}: predicted frames against the dataset: PSNR {result[name]['psnr_mean']:.2f} dB, "
                f"SSIM {result[name]['ssim_mean']:.3f} over {len(rows)} images")
    gt_file = gt_path or (dataset.gt_file if dataset is not None else None)
    if gt_file:
        gt = read_sim(gt_file)
        sp = 2.0 * gt.particle_radius
        rows = []
        for f in range(sim.num_frames):
            g = int(np.argmin(np.abs(gt.times - sim.times[f])))
            if abs(gt.times[g] - sim.times[f]) <= 0.5 / gt.fps + 1e-9:
                rows.append({"time": float(sim.times[f]), "gt_frame": g,
                             **particle_error(sim.positions[f], gt.positions[g], sp)})
        if rows:
            result["particles_vs_gt"] = {"gt": str(gt_file), "spacing": sp, "per_frame": rows,
                                         "chamfer_last": rows[-1]["chamfer"],
                                         "chamfer_mean": float(np.mean([x["chamfer"] for x in rows]))}
            log(f"particles vs ground truth: Chamfer {rows[0]['chamfer']:.3f} spacings at t = {rows[0]['time']:.3g} s "
                f"-> {rows[-1]['chamfer']:.3f} at t = {rows[-1]['time']:.3g} s")
    out = Path(out) if out else sim_path.parent
    out.mkdir(parents=True, exist_ok=True)
    result["plots"] = _plot_continuation(result, out / f"{sim_path.stem}_eval.png")
    atomic_write_text(out / f"{sim_path.stem}_eval.json", json.dumps(result, indent=1))
    log(f"wrote {out / (sim_path.stem + '_eval.json')}")
    return result


def _plot_continuation(result: dict, path: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for split in ("train", "test"):
        if split in result:
            pf = result[split]["per_frame"]
            ax[0].plot([p["time"] for p in pf], [p["psnr"] for p in pf], "o-", ms=3, label=f"{split} views")
    ax[0].set(xlabel="time (s)", ylabel="PSNR (dB)", title="predicted frames vs dataset")
    if "train" in result or "test" in result:
        ax[0].legend()
    if "particles_vs_gt" in result:
        pv = result["particles_vs_gt"]["per_frame"]
        ax[1].plot([x["time"] for x in pv], [x["gt_to_recon"] for x in pv], "o-", ms=3, label="true -> predicted")
        ax[1].plot([x["time"] for x in pv], [x["recon_to_gt"] for x in pv], "s-", ms=3, label="predicted -> true")
        ax[1].legend()
    ax[1].set(xlabel="time (s)", ylabel="mean distance (true spacings)", title="particles vs ground truth")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path.name]


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


def _emd_floor(gt: np.ndarray, spacing: float, samples: int = 1000) -> float:
    perm = np.random.default_rng(1).permutation(len(gt))
    half = min(samples, len(gt) // 2)
    if half == 0:
        return math.nan
    return transport_distance(gt[perm[:half]], gt[perm[half:2 * half]], spacing, samples=half)["emd"]


def particle_stats(r) -> dict:
    """Count, radius (geometric-mean Gaussian scale) and opacity statistics (paper Table 3)."""
    radius = np.exp(np.asarray(r.log_scales, np.float64).mean(1))
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(r.logit_opacity, np.float64)))
    out = {"count": int(r.num_particles)}
    for name, a in (("radius_m", radius), ("opacity", opacity)):
        out[name] = {"mean": float(a.mean()), "median": float(np.median(a)), "p10": float(np.percentile(a, 10)),
                     "p90": float(np.percentile(a, 90))}
    return out


def _flow_summary(rows: list[dict]) -> dict:
    """Means of ``metrics.flow_error`` over the frames whose true flow at the particles is faster
    than a tenth of the clip's fastest (a fluid at rest has no flow to follow)."""
    fast = max((x["true_speed"] for x in rows if math.isfinite(x["true_speed"])), default=0.0)
    moving = [x for x in rows if math.isfinite(x["true_speed"]) and x["true_speed"] > 0.1 * fast > 0]
    if not moving:
        return {"flow_following_mean": math.nan, "flow_following_min_frame": math.nan, "velocity_error_mean": math.nan}
    return {"flow_following_mean": float(np.mean([x["flow_following"] for x in moving])),
            "flow_following_min_frame": float(min(x["flow_following"] for x in moving)),
            "velocity_error_mean": float(np.mean([x["velocity_error"] for x in moving]))}


def energies(model: FluidModel, r, times, states, sim, rest_density: float | None) -> dict:
    """Kinetic, potential and total energy per frame (paper Fig. 5) with the decoder's velocities
    (``states``: ``model.at(t, with_velocity=True)`` for each of ``times``).

    Mass: the rest density (``rest_density``, else the ground truth's, else water's 1000 kg/m^3)
    times the fluid volume recon.h5 gives (``fluid_volume``: the trained particles' SPH estimate,
    ``metrics.particle_volume``; older files: the masks' hull), shared equally by its particles
    (else the rest density times a particle spacing cubed). Potential energy is measured
    from the ground truth's floor (its domain's lowest z), else the reconstruction's domain floor.
    The ground truth's energies use its own velocities and rest density x spacing^3 per particle."""
    rho = float(rest_density or (sim.rest_density if sim is not None else 1000.0))
    n = max(len(model), 1)
    if r.config.get("fluid_volume"):
        mass, src = rho * float(r.config["fluid_volume"]) / n, f"{rho:g} kg/m^3 x the estimated fluid volume " \
                                                              f"{float(r.config['fluid_volume']):.4g} m^3 / {n} particles"
    else:
        sp = float(r.config.get("spacing") or 0.0)
        mass, src = rho * sp ** 3, f"{rho:g} kg/m^3 x spacing^3"
    z_ref = float(sim.domain_min[2]) if sim is not None else float(model.bounds.lo[2])
    gm = sim.rest_density * (2.0 * sim.particle_radius) ** 3 if sim is not None else None
    rows = []
    for t, a in zip(times, states):
        v = a["velocities"].cpu().numpy()
        # the root-mean-square speed: kinetic energy per kilogram, whatever the estimated mass
        row = {"time": float(t), **mechanical_energy(a["means"].cpu().numpy(), v, mass, z_ref),
               "speed_rms": float(np.sqrt((v.astype(np.float64) ** 2).sum(1).mean())) if len(v) else 0.0}
        if sim is not None:
            f = int(np.argmin(np.abs(sim.times - t)))
            gt = mechanical_energy(sim.positions[f], sim.velocities[f], gm, z_ref)
            gv = np.asarray(sim.velocities[f], np.float64)
            row.update({f"gt_{k}": v for k, v in gt.items()},
                       gt_speed_rms=float(np.sqrt((gv ** 2).sum(1).mean())) if len(gv) else 0.0)
        rows.append(row)
    out = {"mass_per_particle": mass, "mass_source": src, "mass_total": mass * len(model), "rest_density": rho,
           "z_ref": z_ref, "velocity_source": "decoder time derivative (analytic)", "per_frame": rows}
    if sim is not None:
        out["gt_mass_total"] = gm * len(sim.positions[0])
    return out


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
    if "energy" in result:
        en = result["energy"]["per_frame"]
        fig, ax = plt.subplots(1, 3, figsize=(11, 3.2))
        for k, (key, title) in enumerate((("kinetic", "kinetic"), ("potential", "potential"), ("total", "total"))):
            ax[k].plot([x["time"] for x in en], [x[key] for x in en], "o-", ms=3, label="reconstruction")
            if f"gt_{key}" in en[0]:
                ax[k].plot([x["time"] for x in en], [x[f"gt_{key}"] for x in en], "s--", ms=3, label="ground truth")
            ax[k].set(xlabel="time (s)", ylabel="energy (J)", title=f"{title} energy")
        ax[0].legend()
        save(fig, "eval_energy.png")
    if "particles_vs_gt" in result:
        pv = result["particles_vs_gt"]["per_frame"]
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        ax[0].plot([x["time"] for x in pv], [x["gt_to_recon"] for x in pv], "o-", ms=3, label="true -> recon")
        ax[0].plot([x["time"] for x in pv], [x["recon_to_gt"] for x in pv], "s-", ms=3, label="recon -> true")
        ax[0].plot([x["time"] for x in pv], [x["emd"] for x in pv], "^-", ms=3, label="earth mover's")
        ax[0].axhline(1.0, color="gray", lw=0.8, ls="--")
        ax[0].set(xlabel="time (s)", ylabel="mean distance (true spacings)", title="particle error")
        ax[0].legend()
        ax[1].plot([x["time"] for x in pv], [x["particles_recon"] for x in pv], label="reconstructed")
        ax[1].plot([x["time"] for x in pv], [x["particles_gt"] for x in pv], label="true")
        ax[1].set(xlabel="time (s)", ylabel="particles", title="particle counts")
        ax[1].legend()
        save(fig, "eval_particles.png")
    if "upsample" in result:
        u = result["upsample"]
        from .resample import METHODS

        fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        names = list(METHODS) + (["truth"] if "truth" in u["jitter"] else [])
        ax[0].bar(names, [u["jitter"][m] for m in names], color=["C0", "C1", "C2", "gray"][:len(names)])
        ax[0].set(ylabel="std of adjacent-frame differences", title=f"jitter at {u['fps']:.4g} fps (x{u['k']})")
        if "heldout" in u:
            ax[1].bar(list(METHODS), [u["heldout"][m]["psnr"] for m in METHODS], color=["C0", "C1", "C2"])
            lo = min(u["heldout"][m]["psnr"] for m in METHODS)
            ax[1].set_ylim(max(lo - 3, 0), None)
        else:
            ax[1].text(0.5, 0.5, "no frame held out in time\n(reconstruct --frames ::2 holds out every other)",
                       ha="center", va="center", transform=ax[1].transAxes)
        ax[1].set(ylabel="PSNR (dB)", title=f"frames held out in time ({len(u['heldout_times'])})")
        save(fig, "eval_upsample.png")
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


__all__ = ["evaluate", "evaluate_continuation", "read_metrics", "plot_eval"]
