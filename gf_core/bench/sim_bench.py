"""``gf-cli bench sim``: each solver over a sweep of accuracy settings and particle counts;
``--engine``: DFSPH's native and torch paths side by side over particle counts, and the neighbour
search alone.

Per run: the density error measured independently after every step (mean and max of
max(rho/rho0 - 1, 0) with the cubic spline, walls included), mechanical energy, and wall time.
Summaries give error against seconds of computation per simulated second; the plot shows the
summary points and each run's error-vs-wall-clock trace.
"""

from __future__ import annotations

import numpy as np

from ..sim import simulate

SWEEPS = {
    "dfsph": [("cfl 0.8, tol 0.1%", {"cfl": 0.8, "density_tol": 1e-3}),
              ("cfl 0.4, tol 0.05%", {"cfl": 0.4, "density_tol": 5e-4}),
              ("cfl 0.2, tol 0.01%", {"cfl": 0.2, "density_tol": 1e-4})],
    "pbf": [("dt 1/120, 2 it", {"dt": 1 / 120, "iterations": 2}),
            ("dt 1/240, 4 it", {"dt": 1 / 240, "iterations": 4}),
            ("dt 1/480, 8 it", {"dt": 1 / 480, "iterations": 8})],
}


def bench_sim(solvers, counts, *, scene: str = "dam_break", seconds: float = 0.5, fps: float = 30.0,
              device: str = "cpu", log=print):
    records, traces = [], []
    for n in counts:
        for solver in solvers:
            for label, overrides in SWEEPS[solver]:
                sim, res = simulate(scene, solver=solver, particles=n, fps=fps, seconds=seconds,
                                    device=device, **overrides)
                steps = res.steps
                wall = steps[-1]["wall_s"] if steps else 0.0
                dm = np.array([s["density_err_mean"] for s in steps])
                dx = np.array([s["density_err_max"] for s in steps])
                e = np.array([s["kinetic"] + s["potential"] for s in steps])
                e0 = float(sim.stats["kinetic"][0] + sim.stats["potential"][0])
                rec = {"scene": scene, "solver": solver, "setting": label, "particles": sim.num_particles,
                       "simulated_s": seconds, "steps": len(steps), "wall_s": wall,
                       "wall_per_sim_s": wall / seconds, "density_err_mean": float(dm.mean()),
                       "density_err_max": float(dx.max()),
                       "energy_change_rel": float((e[-1] - e0) / abs(e0)) if abs(e0) > 0 else 0.0,
                       "front_x_final": float(sim.positions[-1][:, 0].max())}
                records.append(rec)
                traces.append({"label": f"{solver} {label} N={sim.num_particles}",
                               "wall_s": [s["wall_s"] for s in steps], "density_err_mean": dm.tolist()})
                log(f"{solver:>6} {label:<20} N={sim.num_particles:<6} {wall:7.1f} s  mean rho err "
                    f"{100 * rec['density_err_mean']:.3f}%  max {100 * rec['density_err_max']:.2f}%")
    return records, traces


def bench_engine(counts, backends=("native", "torch"), *, scene: str = "dam_break", seconds: float = 0.1,
                 fps: float = 50.0, log=print):
    """DFSPH at its defaults (0.01 % density tolerance, CFL 0.4) on ``scene`` for each particle count
    and pair-sum backend: wall seconds per simulated second (the run, not the settling before it),
    the independently measured density error, steps and Jacobi iterations; the ratio of each
    backend's time to the first's, and how the cost grows with the particle count (the exponent
    between consecutive counts)."""
    records = []
    for n in counts:
        for be in backends:
            sim, res = simulate(scene, solver="dfsph", particles=n, fps=fps, seconds=seconds, backend=be)
            steps = res.steps
            wall = steps[-1]["wall_s"] if steps else 0.0
            rec = {"scene": scene, "backend": be, "particles": sim.num_particles, "simulated_s": seconds,
                   "steps": len(steps), "wall_s": wall, "wall_per_sim_s": wall / seconds,
                   "density_err_mean": float(np.mean([s["density_err_mean"] for s in steps])),
                   "iterations_mean": float(np.mean([s["iterations"] for s in steps])),
                   "divergence_iterations_mean": float(np.mean([s["divergence_iterations"] for s in steps]))}
            # the cost of one Jacobi iteration (both solves): steps and iterations per simulated second grow
            # with N by themselves (dt ~ spacing, deeper columns need more iterations)
            total_it = sum(s["iterations"] + s["divergence_iterations"] for s in steps)
            rec["ms_per_iteration"] = 1e3 * wall / max(total_it, 1)
            first = next(r for r in records + [rec] if r["particles"] == rec["particles"])
            rec["time_vs_first_backend"] = wall / first["wall_s"] if first["wall_s"] > 0 else float("nan")
            prev = [r for r in records if r["backend"] == be]
            if prev and prev[-1]["particles"] != rec["particles"] and prev[-1]["wall_per_sim_s"] > 0:
                lnN = np.log(rec["particles"] / prev[-1]["particles"])
                rec["growth_exponent"] = float(np.log(rec["wall_per_sim_s"] / prev[-1]["wall_per_sim_s"]) / lnN)
                rec["iteration_growth_exponent"] = float(np.log(rec["ms_per_iteration"] / prev[-1]["ms_per_iteration"])
                                                         / lnN)
            records.append(rec)
            log(f"dfsph {be:>6} N={rec['particles']:<6} {wall:7.2f} s for {seconds} s simulated "
                f"({rec['wall_per_sim_s']:.1f} s per simulated s), {len(steps)} steps, "
                f"{rec['iterations_mean']:.1f} density iterations, mean rho err {100 * rec['density_err_mean']:.3f}%")
    return records


def bench_neighbours(n: int = 50000, k: int = 64, repeats: int = 7, log=print) -> list:
    """The neighbour search alone on ``n`` particles jittered on a lattice of spacing s (shuffled:
    input order is not spatial), h = 2.5 s (about 60 neighbours): native K-nearest (sorted rows and
    not), native fixed-radius CSR lists, the native kernel sum, the torch grid, and scipy's cKDTree
    when scipy is installed."""
    import math

    import torch

    from ..sph.neighbors import knn, knn_torch, neighbor_lists, neighbor_pairs_torch
    from .. import native
    from .common import median_time

    side = math.ceil(n ** (1 / 3))
    g = torch.Generator().manual_seed(0)
    ax = torch.arange(side, dtype=torch.float32)
    P = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = ((P + 0.2 * torch.randn(P.shape, generator=g)) * 0.01)[torch.randperm(n, generator=g)].contiguous()
    h = 0.025
    ops = [("native knn, rows sorted", lambda: knn(x, k, h, backend="native")),
           ("native knn, rows unsorted", lambda: knn(x, k, h, backend="native", sorted=False)),
           ("native radius lists (CSR)", lambda: neighbor_lists(x, h)),
           ("native kernel sum (no pairs stored)", lambda: native.load().kernel_sum(x, x, [], h, 1, True)),
           ("torch grid radius pairs", lambda: neighbor_pairs_torch(x, h)),
           ("torch grid knn", lambda: knn_torch(x, k, h))]
    try:
        from scipy.spatial import cKDTree

        xn = x.numpy()
        ops.append(("scipy cKDTree build + query (k+1, workers=2)",
                    lambda: cKDTree(xn).query(xn, k=k + 1, distance_upper_bound=h, workers=2)))
    except ImportError:
        pass
    rows = []
    for name, f in ops:
        t = median_time(f, repeats if not name.startswith("torch") else 3, warmup=1)
        rows.append({"operation": name, "particles": n, "k": k, "seconds": t})
        log(f"{name:<46} {1e3 * t:8.1f} ms")
    return rows


def bench_prediction(solvers, particles: int, *, scene: str = "water_sphere", start_frame: int = 6,
                     frames: int = 12, fps: float = 30.0, noise: float = 0.0, device: str = "cpu", log=print):
    """Prediction error against simulation cost: a reference run of ``scene`` (DFSPH at its
    strictest sweep setting) is cut at ``start_frame``; from that state (optionally perturbed by
    ``noise`` particle spacings), each solver and sweep setting predicts ``frames`` frames the way
    ``gf-cli predict`` does (rest state estimated from the particles), and its particles are
    compared with the reference's at every frame (both Chamfer directions, in spacings) against
    the wall-clock seconds spent so far."""
    import time

    from ..eval.metrics import particle_error
    from ..downstream.predict import State, continue_state

    ref_label, ref_settings = SWEEPS["dfsph"][-1]
    ref, _ = simulate(scene, solver="dfsph", particles=particles, fps=fps, seconds=(start_frame + frames) / fps,
                      device=device, **ref_settings)
    sp = 2.0 * ref.particle_radius
    x0 = ref.positions[start_frame].astype(np.float64)
    if noise:
        x0 = x0 + np.random.default_rng(0).normal(scale=noise * sp, size=x0.shape)
    state = State(positions=x0, velocities=ref.velocities[start_frame], source_index=np.arange(ref.num_particles),
                  time=float(ref.times[start_frame]), domain=(np.asarray(ref.domain_min), np.asarray(ref.domain_max)))
    records = []
    for solver in solvers:
        for label, settings in SWEEPS[solver]:
            walls = [0.0]
            t0 = time.perf_counter()
            sim, rep = continue_state(state, frames=frames, fps=fps, solver=solver, device=device,
                                      solver_settings=settings,
                                      progress=lambda f, n, t, last: walls.append(time.perf_counter() - t0))
            err = [particle_error(sim.positions[k], ref.positions[start_frame + k], sp) for k in range(frames + 1)]
            records.append({"scene": scene, "solver": solver, "setting": label, "particles": ref.num_particles,
                            "start_time_s": state.time, "frames": frames, "noise_spacings": noise,
                            "steps": rep["steps"], "wall_s": rep["wall_seconds"],
                            "spacing_estimated": rep["spacing"], "spacing_true": sp,
                            "chamfer_final": err[-1]["chamfer"],
                            "chamfer_mean": float(np.mean([e["chamfer"] for e in err[1:]])),
                            "trace_wall_s": walls, "trace_chamfer": [e["chamfer"] for e in err]})
            log(f"{solver:>6} {label:<20} {rep['wall_seconds']:6.1f} s  Chamfer after {frames} frames "
                f"{err[-1]['chamfer']:.3f} spacings (reference: dfsph {ref_label})")
    return records


def plot_engine(records, path):
    """Seconds per simulated second against particle count (log-log) and density error against
    seconds, one line per backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for be in dict.fromkeys(r["backend"] for r in records):
        rs = [r for r in records if r["backend"] == be]
        ax[0].plot([r["particles"] for r in rs], [r["wall_per_sim_s"] for r in rs], "o-", label=be)
        ax[1].plot([r["wall_per_sim_s"] for r in rs], [r["density_err_mean"] for r in rs], "o-", label=be)
        for r in rs:
            ax[1].annotate(str(r["particles"]), (r["wall_per_sim_s"], r["density_err_mean"]), fontsize=7)
    ax[0].set(xscale="log", yscale="log", xlabel="fluid particles", ylabel="wall s per simulated s",
              title=f"DFSPH {records[0]['scene']}, tolerance 0.01 %")
    ax[1].set(xscale="log", xlabel="wall s per simulated s", ylabel="mean density error (measured)",
              title="error vs run time")
    for a in ax:
        a.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_prediction(records, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for solver in sorted({r["solver"] for r in records}):
        rs = [r for r in records if r["solver"] == solver]
        ax[0].plot([r["wall_s"] for r in rs], [r["chamfer_final"] for r in rs], "o-", label=solver)
        for r in rs:
            ax[0].annotate(r["setting"], (r["wall_s"], r["chamfer_final"]), fontsize=7)
            ax[1].plot(r["trace_wall_s"], r["trace_chamfer"], lw=1, label=f"{solver} {r['setting']}")
    ax[0].set(xlabel="wall-clock seconds", ylabel="Chamfer at the last frame (spacings)",
              title=f"prediction error vs run time ({records[0]['frames']} frames)")
    ax[0].set_xscale("log")
    ax[0].legend()
    ax[1].set(xlabel="wall-clock seconds", ylabel="Chamfer vs reference (spacings)", title="per-frame traces")
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot(records, traces, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    keys = sorted({(r["solver"], r["particles"]) for r in records})
    for solver, n in keys:
        rs = [r for r in records if r["solver"] == solver and r["particles"] == n]
        ax[0].plot([r["wall_per_sim_s"] for r in rs], [100 * r["density_err_mean"] for r in rs], "o-",
                   label=f"{solver}, N={n}")
        for r in rs:
            ax[0].annotate(r["setting"], (r["wall_per_sim_s"], 100 * r["density_err_mean"]), fontsize=7)
    ax[0].set_xscale("log")
    ax[0].set_yscale("log")
    ax[0].set_xlabel("wall-clock seconds per simulated second")
    ax[0].set_ylabel("mean density error (%)")
    ax[0].set_title("error vs run time")
    ax[0].legend(fontsize=8)
    for t in traces:
        ax[1].plot(t["wall_s"], [100 * d for d in t["density_err_mean"]], lw=0.8, label=t["label"])
    ax[1].set_xlabel("wall-clock seconds")
    ax[1].set_ylabel("mean density error after each step (%)")
    ax[1].set_yscale("symlog", linthresh=1e-3)
    ax[1].set_title("per-step error traces")
    ax[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
