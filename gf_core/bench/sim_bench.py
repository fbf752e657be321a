"""``gf-cli bench sim``: each solver over a sweep of accuracy settings and particle counts.

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


def bench_prediction(solvers, particles: int, *, scene: str = "water_sphere", start_frame: int = 6,
                     frames: int = 12, fps: float = 30.0, noise: float = 0.0, device: str = "cpu", log=print):
    """Prediction error against simulation cost: a reference run of ``scene`` (DFSPH at its
    strictest sweep setting) is cut at ``start_frame``; from that state (optionally perturbed by
    ``noise`` particle spacings), each solver and sweep setting predicts ``frames`` frames the way
    ``gf-cli predict`` does (rest state estimated from the particles), and its particles are
    compared with the reference's at every frame (both Chamfer directions, in spacings) against
    the wall-clock seconds spent so far."""
    import time

    from ..metrics import particle_error
    from ..predict import State, continue_state

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
