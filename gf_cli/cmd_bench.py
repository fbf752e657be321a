"""``gf-cli bench {render,sim,reconstruct,gpu,decoder}``: figures and ratios, printed as tables and written as JSON."""

from __future__ import annotations

import json
import os
from pathlib import Path


def _ints(s: str, flag: str = "--particles", minimum: int = 1) -> list[int]:
    """A comma-separated list of positive integers; errors name the option."""
    from gf_core.errors import InputError

    out = []
    for x in s.split(","):
        x = x.strip()
        if not x:
            continue
        try:
            v = float(x)
        except ValueError:
            raise InputError(flag, f"{x!r} is not a number (expected a comma-separated list like 1000,20000)") from None
        if v != int(v) or v < minimum:
            raise InputError(flag, f"values must be integers >= {minimum}, got {x}")
        out.append(int(v))
    if not out:
        raise InputError(flag, "needs at least one value")
    return out


def _check_common(args, out_is_file: bool = True) -> None:
    from gf_core.errors import InputError

    from .options import check_out_file

    if getattr(args, "repeats", 1) < 1:
        raise InputError("--repeats", f"must be >= 1, got {args.repeats}")
    if out_is_file:
        check_out_file(args.out)
    elif args.out.exists() and not args.out.is_dir():
        raise InputError(args.out, "--out must be a folder, and this is a file")


def register(sub):
    p = sub.add_parser("bench", help="benchmarks: renderer backends, simulators (error vs time)",
                       description="Benchmarks that print tables and write JSON (and plots).")
    bsub = p.add_subparsers(dest="bench", metavar="BENCH")
    bsub.required = True
    r = bsub.add_parser("render", help="renderer backends x particle counts x resolutions",
                        description="Times forward and forward+backward of each renderer backend "
                                    "(median of repeats) and reports the max difference between "
                                    "backends. The scene is documented in gf_core/bench/render_bench.py.")
    r.add_argument("--backends", default="native,reference", help="comma-separated (default native,reference)")
    r.add_argument("--particles", default="1000,20000,50000,200000",
                   help="comma-separated particle counts (default 1000,20000,50000,200000)")
    r.add_argument("--resolutions", default="128,256,400,800",
                   help="comma-separated image sizes (default 128,256,400,800)")
    r.add_argument("--repeats", type=int, default=5, help="timed repeats, median reported (default 5)")
    r.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    r.add_argument("--reference-max-work", type=float, default=1.2e10,
                   help="skip the reference backend above particles x pixels (default 1.2e10)")
    r.add_argument("--out", type=Path, default=Path("bench_render.json"), help="JSON output (default bench_render.json)")
    r.set_defaults(func=run_render)
    q = bsub.add_parser("sim", help="simulators: error vs run time over accuracy sweeps; stability suite",
                        description="Runs DFSPH and PBF over a sweep of accuracy settings (CFL factor "
                                    "and tolerance; substep and iterations) and particle counts, measures "
                                    "the density error itself after every step, energy and wall time, "
                                    "and writes JSON and a PNG of error vs seconds. --stability also runs "
                                    "the stability suite.")
    q.add_argument("--solvers", default="dfsph,pbf", help="comma-separated (default dfsph,pbf)")
    q.add_argument("--particles", default="1000,4000", help="comma-separated particle counts (default 1000,4000)")
    q.add_argument("--scene", default="dam_break", help="scene preset (default dam_break)")
    q.add_argument("--seconds", type=float, default=0.5, help="simulated seconds per run (default 0.5)")
    q.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    q.add_argument("--stability", action="store_true", help="also run the stability suite")
    q.add_argument("--prediction", action="store_true",
                   help="instead of the accuracy sweep: prediction error against simulation cost (each solver setting "
                        "continues a reference water_sphere run (first --particles count) from frame 6 for 12 "
                        "frames, as gf-cli predict does; Chamfer vs the reference against wall-clock seconds)")
    q.add_argument("--engine", action="store_true",
                   help="instead of the accuracy sweep: DFSPH at its defaults with each --backends pair-sum path at each "
                        "--particles count (seconds per simulated second, density error, growth with N), and the "
                        "neighbour search alone over --neighbours particles")
    q.add_argument("--backends", default="native,torch", help="with --engine: comma-separated (default native,torch)")
    q.add_argument("--neighbours", type=int, default=50000,
                   help="with --engine: particles for the neighbour-search timing, K = 64 (default 50000; 0 skips it)")
    q.add_argument("--out", type=Path, default=Path("bench_sim"), help="output folder (JSON + PNG)")
    q.set_defaults(func=run_sim)
    g = bsub.add_parser("gpu", help="CUDA figures: renderer fwd+bwd (vs gsplat if installed), K-nearest SPH density",
                        description="Times the CUDA renderer's forward+backward on the bench-render scene (and "
                                    "gsplat's rasterization on the same particles when gsplat is importable), and "
                                    "the K-nearest SPH density with its gradient. Needs a CUDA GPU.")
    g.add_argument("--particles", type=int, default=50000, help="particles (default 50000)")
    g.add_argument("--resolution", type=int, default=400, help="image width and height (default 400)")
    g.add_argument("--k", type=int, default=64, help="neighbours for the density (default 64)")
    g.add_argument("--repeats", type=int, default=50, help="timed repeats, median reported (default 50)")
    g.add_argument("--tiles", default="8,16", help="renderer tile sizes to time, comma-separated; the first is "
                                                   "profiled and compared with gsplat (default 8,16)")
    g.add_argument("--out", type=Path, default=Path("bench_gpu.json"), help="JSON output (default bench_gpu.json)")
    g.set_defaults(func=run_gpu)
    c = bsub.add_parser("reconstruct", help="whole method: held-out PSNR and particle error against run time",
                        description="Reconstructs one dataset for every pair of iteration budget and particle budget, "
                                    "evaluates each run (held-out PSNR/SSIM, Chamfer against the dataset's particles "
                                    "when it has them, density spread) and writes bench_reconstruct.json and "
                                    "error_vs_time.png (points, Pareto front, training traces).")
    c.add_argument("dataset", type=Path, help="dataset folder")
    c.add_argument("--iterations", default="1000,3000", help="comma-separated iteration budgets (default 1000,3000)")
    c.add_argument("--particles", default="2000,4000", help="comma-separated particle budgets (default 2000,4000)")
    c.add_argument("--preset", default="water", choices=["water", "honey", "smoke"], help="preset (default water)")
    c.add_argument("--config", type=Path, default=None, help="TOML file overriding preset keys (default: none)")
    c.add_argument("--frames", default=None, metavar="START:END:STEP", help="train on these frame times (default all)")
    c.add_argument("--per-frame", action="store_true",
                   help="fit every selected frame on its own (a static scene, no time model) for each budget pair: "
                        "the per-frame reference for a time-continuous reconstruction; writes per_frame.png")
    c.add_argument("--time-budget", type=float, default=0.0, metavar="SECONDS",
                   help="each run stops after this many seconds instead of at its iterations; with --per-frame the "
                        "frames share it equally (default: none)")
    c.add_argument("--seed", type=int, default=None, help="reconstruction seed (default: the preset's)")
    c.add_argument("--grayscale", action="store_true", help="one colour channel, as reconstruct (default: off)")
    c.add_argument("--background-removal", choices=["difference", "xor"], default=None,
                   help="grayscale footage: as reconstruct (default: none)")
    size = c.add_mutually_exclusive_group()
    size.add_argument("--resolution", type=int, default=None, metavar="W", help="images W pixels wide, as reconstruct")
    size.add_argument("--downscale", type=float, default=None, metavar="K", help="images K times smaller, as reconstruct")
    c.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    c.add_argument("--out", type=Path, default=Path("bench_reconstruct"), help="output folder (runs, JSON, PNG)")
    c.set_defaults(func=run_reconstruct)
    m = bsub.add_parser("scenes", help="the scene matrix: every scene made, reconstructed with the default preset, judged",
                        description="Makes every scene of a suite with gf-cli simulate and render-dataset, reconstructs "
                                    "each with the default preset and the suite's time budget, evaluates it (held-out "
                                    "PSNR/SSIM mean and worst frame, both Chamfer directions, coverage, particles outside "
                                    "the container, energies against the truth) and fits every frame on its own (3DGS) "
                                    "at the same total time. Prints the table against the suite's targets; writes "
                                    "bench_scenes.json and a plot per scene. Steps already complete are skipped.")
    m.add_argument("--suite", type=Path, default=None, help="suite TOML (default: gf_core/bench/scenes.toml)")
    m.add_argument("--quick", action="store_true", help="the suite's [quick] sizes: every scene kind, tiny (minutes)")
    m.add_argument("--only", default=None, metavar="NAME[,NAME]", help="these scenes only (default: all)")
    m.add_argument("--seeds", default=None, metavar="S[,S]", help="reconstruction seeds (default: the suite's)")
    m.add_argument("--no-per-frame", action="store_true", help="skip the per-frame 3DGS fits (default: run them)")
    m.add_argument("--out", type=Path, default=Path("bench_scenes"), help="output folder (datasets, runs, JSON, PNG)")
    where = m.add_mutually_exclusive_group()
    where.add_argument("--local", type=int, default=None, metavar="N",
                       help="N jobs at a time on this machine (default 1: every reconstruction has the whole machine)")
    where.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="the jobs as Ray tasks on this cluster ('auto': the one `ray start` made here)")
    m.add_argument("--cpus-per-job", type=float, default=None, metavar="K",
                   help="threads (and Ray CPUs) of each reconstruction, fit and evaluation (default: this machine's "
                        "cores / N; with --ray 2)")
    m.set_defaults(func=run_scenes)
    d = bsub.add_parser("decoder", help="numpy decoder (the Blender extension's) against the torch one",
                        description="Times one evaluation of the time-continuous decoder (paper Eq. 4, default "
                                    "dimensions) for all particles at one time: numpy float32 as the Blender "
                                    "extension runs it (positions only, and with velocities), and torch on the CPU; "
                                    "checks that they agree.")
    d.add_argument("--particles", default="10000,50000", help="comma-separated counts (default 10000,50000)")
    d.add_argument("--repeats", type=int, default=10, help="timed repeats, median reported (default 10)")
    d.add_argument("--out", type=Path, default=Path("bench_decoder.json"), help="JSON output (default bench_decoder.json)")
    d.set_defaults(func=run_decoder)


def run_render(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.render_bench import bench_render
    from gf_core.formats.hdf5 import atomic_write_text

    from gf_core.errors import InputError

    from .options import check_device

    backends = [b for b in args.backends.split(",") if b]
    for b in backends:
        if b not in ("native", "reference"):
            raise InputError("--backends", f"unknown backend {b!r} (native, reference)")
    counts, resolutions = _ints(args.particles), _ints(args.resolutions, "--resolutions", 8)
    _check_common(args)
    check_device(args.device)
    need = max(counts) * 4 * 60 + max(resolutions) ** 2 * 4 * 40  # parameters, grads, images: bytes
    if args.device == "cpu":
        from gf_core.limits import require_memory

        require_memory("--particles", f"{max(counts)} particles at {max(resolutions)}^2", need)
    recs = bench_render(backends, counts, resolutions, repeats=args.repeats,
                        device=args.device, reference_max_work=args.reference_max_work)
    info = machine()
    print()
    print(f"machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} "
          f"({info['torch_threads']} threads)")
    print(table(recs, [("backend", "backend", "s"), ("particles", "particles", "d"),
                       ("resolution", "res", "d"), ("forward_s", "fwd s", ".4f"),
                       ("forward_backward_s", "fwd+bwd s", ".4f"), ("speedup_fwd_bwd", "speedup", ".1f"),
                       ("max_abs_diff_color", "max|dC|", ".1e"), ("max_rel_diff_grads", "max rel dgrad", ".1e")]))
    atomic_write_text(args.out, json.dumps({"machine": info, "records": recs}, indent=1))
    print(f"\nwrote {args.out}")
    return 0


def run_sim(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.sim_bench import bench_sim, plot
    from gf_core.formats.hdf5 import atomic_write_text

    from gf_core.errors import InputError

    from .options import check_device

    solvers = [s for s in args.solvers.split(",") if s]
    from gf_core.sim.solvers import solver

    for s in solvers:
        solver(s, "--solvers")
    counts = _ints(args.particles)
    if not args.seconds > 0:
        raise InputError("--seconds", f"must be a positive number, got {args.seconds}")
    check_device(args.device)
    _check_common(args, out_is_file=False)
    args.out.mkdir(parents=True, exist_ok=True)
    out = {"machine": machine()}
    if args.engine:
        from gf_core.bench.sim_bench import bench_engine, bench_neighbours, plot_engine

        backends = [b for b in args.backends.split(",") if b]
        for b in backends:
            if b not in ("native", "torch"):
                raise InputError("--backends", f"unknown backend {b!r} (native, torch)")
        if args.neighbours < 0:
            raise InputError("--neighbours", f"must be >= 0, got {args.neighbours}")
        eng = bench_engine(counts, backends, scene=args.scene, seconds=args.seconds)
        out["engine"] = eng
        print()
        print(table(eng, [("backend", "backend", "s"), ("particles", "N", "d"), ("steps", "steps", "d"),
                          ("wall_s", "wall s", ".2f"), ("wall_per_sim_s", "s per sim s", ".1f"),
                          ("time_vs_first_backend", f"time / {backends[0]}", ".2f"),
                          ("growth_exponent", "cost ~ N^", ".2f"), ("iterations_mean", "iters", ".1f"),
                          ("ms_per_iteration", "ms/iteration", ".2f"),
                          ("iteration_growth_exponent", "per-iteration ~ N^", ".2f"),
                          ("density_err_mean", "mean rho err", ".2e")]))
        plot_engine(eng, args.out / "engine_cost_vs_particles.png")
        if args.neighbours:
            print()
            out["neighbours"] = bench_neighbours(args.neighbours)
    elif args.prediction:
        from gf_core.bench.sim_bench import bench_prediction, plot_prediction

        pred = bench_prediction(solvers, counts[0], device=args.device)
        out["prediction"] = pred
        print()
        print(table(pred, [("solver", "solver", "s"), ("setting", "setting", "s"), ("particles", "N", "d"),
                           ("steps", "steps", "d"), ("wall_s", "wall s", ".1f"),
                           ("chamfer_mean", "Chamfer mean", ".3f"), ("chamfer_final", "Chamfer last", ".3f")]))
        plot_prediction(pred, args.out / "prediction_error_vs_time.png")
    else:
        recs, traces = bench_sim(solvers, counts, scene=args.scene, seconds=args.seconds, device=args.device)
        print()
        print(table(recs, [("solver", "solver", "s"), ("setting", "setting", "s"), ("particles", "N", "d"),
                           ("steps", "steps", "d"), ("wall_s", "wall s", ".1f"),
                           ("wall_per_sim_s", "s per sim s", ".1f"), ("density_err_mean", "mean rho err", ".2e"),
                           ("density_err_max", "max rho err", ".2e"), ("energy_change_rel", "dE/E0", "+.3f")]))
        out.update(records=recs, traces=traces)
        plot(recs, traces, args.out / "error_vs_time.png")
    if args.stability:
        from gf_core.sim.stability import CASES, run_case

        stab = [run_case(c, s) for c in CASES for s in solvers]
        out["stability"] = stab
        print()
        print(table(stab, [("case", "case", "s"), ("solver", "solver", "s"), ("particles", "N", "d"),
                           ("ok", "ok", "") , ("max_speed_rel", "vmax/sqrt(gH)", ".3f"),
                           ("density_err_mean", "rho err", ".2e"), ("wall_s", "wall s", ".1f")]))
        for r in stab:
            if r.get("refused"):
                print(f"  {r['case']} ({r['solver']}): refused up front: {r['refused']}")
    atomic_write_text(args.out / "bench_sim.json", __import__("json").dumps(out, indent=1))
    print(f"\nwrote {args.out / 'bench_sim.json'} and the plot in {args.out}")
    return 0


def run_reconstruct(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.recon_bench import bench_reconstruct, plot, plot_per_frame
    from gf_core.errors import InputError
    from gf_core.formats.hdf5 import atomic_write_text
    from gf_core.recon.config import make_config

    from .options import check_device
    from .options import parse_frames

    its = _ints(args.iterations, "--iterations")
    ns = _ints(args.particles, "--particles")
    check_device(args.device)
    _check_common(args, out_is_file=False)
    if not args.dataset.is_dir():
        raise InputError(args.dataset, "is not a dataset folder")
    make_config(args.preset, args.config)  # a bad config fails before any run
    frames = parse_frames(args.frames) if args.frames is not None else None
    if not (args.time_budget >= 0 and args.time_budget < float("inf")):
        raise InputError("--time-budget", f"must be a non-negative number of seconds, got {args.time_budget}")
    args.out.mkdir(parents=True, exist_ok=True)
    recs = bench_reconstruct(args.dataset, args.out, iterations=its, particles=ns, preset=args.preset,
                             config_file=args.config, device=args.device, frames=frames, per_frame=args.per_frame,
                             time_budget=args.time_budget, seed=args.seed,
                             load_options=dict(grayscale=args.grayscale, background_removal=args.background_removal,
                                               resolution=args.resolution, downscale=args.downscale))
    cols = [("time", "frame s", ".4f")] if args.per_frame else []
    cols += [("iterations_budget", "it budget", "d"), ("particle_budget", "N budget", "d"), ("iterations", "it", "d"),
            ("particles", "N", "d"), ("wall_s", "wall s", ".1f"), ("train_psnr", "train PSNR", ".2f")]
    if recs[0]["test_psnr"] is not None:
        cols += [("test_psnr", "held-out PSNR", ".2f"), ("test_ssim", "SSIM", ".3f")]
    if "chamfer" in recs[0]:
        cols += [("gt_to_recon", "true->recon", ".3f"), ("recon_to_gt", "recon->true", ".3f")]
    if "density_corr" in recs[0]:
        cols += [("density_corr", "density corr", ".3f")]
    cols += [("density_std", "density std", ".3f")]
    print()
    print(table(recs, cols))
    png = args.out / ("per_frame.png" if args.per_frame else "error_vs_time.png")
    (plot_per_frame if args.per_frame else plot)(recs, png)
    atomic_write_text(args.out / "bench_reconstruct.json",
                      json.dumps({"machine": machine(), "dataset": str(args.dataset), "per_frame": args.per_frame,
                                  "records": recs}, indent=1))
    if args.per_frame:
        import numpy as np

        for key, name in (("test_psnr", "held-out PSNR"), ("train_psnr", "training PSNR")):
            vals = [r[key] for r in recs if r[key] is not None]
            if vals:
                print(f"{name} over the frames: mean {np.mean(vals):.2f} dB, worst {np.min(vals):.2f} dB")
    print(f"\nwrote {args.out / 'bench_reconstruct.json'} and {png}")
    return 0


def run_gpu(args) -> int:
    import torch

    from gf_core.bench.common import machine
    from gf_core.bench.gpu_bench import bench_density, bench_renderer
    from gf_core.errors import InputError
    from gf_core.formats.hdf5 import atomic_write_text

    if not torch.cuda.is_available():
        raise InputError("gf-cli bench gpu", "needs a CUDA GPU, and torch sees none")
    for name in ("particles", "resolution", "k", "repeats"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name}", f"must be >= 1, got {getattr(args, name)}")
    tiles = _ints(args.tiles, "--tiles")
    for t in tiles:
        if t < 1 or (t * t) % 32:
            raise InputError("--tiles", f"tile {t}: tile * tile must be a positive multiple of 32 (8, 16, 24, ...)")
    rec = {"machine": machine(), "renderer": bench_renderer(args.particles, args.resolution, args.repeats, tiles),
           "density": bench_density(args.particles, args.k, args.repeats)}
    atomic_write_text(args.out, json.dumps(rec, indent=1))
    print(f"wrote {args.out}")
    return 0


def run_decoder(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.decoder_bench import bench_decoder
    from gf_core.formats.hdf5 import atomic_write_text

    counts = _ints(args.particles)
    _check_common(args)
    rows = [bench_decoder(n, args.repeats) for n in counts]
    print(table(rows, [("particles", "particles", "d"), ("numpy_ms", "numpy ms", ".1f"),
                       ("numpy_velocity_ms", "numpy+velocity ms", ".1f"), ("torch_ms", "torch ms", ".1f"),
                       ("ratio_numpy_torch", "numpy/torch", ".2f"), ("max_abs_diff", "max |numpy-torch|", ".1e")]))
    atomic_write_text(args.out, json.dumps({"machine": machine(), "rows": rows}, indent=1))
    print(f"wrote {args.out}")
    return 0


def run_scenes(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.scene_bench import COLUMNS, bench_scenes, load_suite, plot_scenes, table_rows
    from gf_core.formats.hdf5 import atomic_write_text

    _check_common(args, out_is_file=False)
    only = [x.strip() for x in args.only.split(",") if x.strip()] if args.only else None
    seeds = _ints(args.seeds, "--seeds", 0) if args.seeds else None
    suite = load_suite(args.suite, quick=args.quick, only=only)
    args.out.mkdir(parents=True, exist_ok=True)
    from gf_core.batch import LocalExecutor, RayExecutor
    from gf_core.errors import InputError

    if args.local is not None and args.local < 1:
        raise InputError("--local", f"must be at least 1, got {args.local}")
    if args.cpus_per_job is not None and not args.cpus_per_job > 0:
        raise InputError("--cpus-per-job", f"must be > 0, got {args.cpus_per_job}")
    n = args.local or 1
    cpus = args.cpus_per_job or (2.0 if args.ray else max(1, (os.cpu_count() or 1) // n))
    ex = RayExecutor(args.ray) if args.ray else LocalExecutor(n)
    recs = bench_scenes(args.out, suite, seeds=seeds, per_frame=not args.no_per_frame, executor=ex, cpus=cpus)
    print()
    cols = [c for c in COLUMNS if any(r.get(c[0]) is not None for r in recs) or c[0] in ("scene", "missed")]
    print(table(table_rows(recs), cols))
    plots = plot_scenes(recs, args.out)
    atomic_write_text(args.out / "bench_scenes.json",
                      json.dumps({"machine": machine(), "suite": suite, "records": recs}, indent=1))
    print(f"\nwrote {args.out / 'bench_scenes.json'} and {len(plots)} plots in {args.out}")
    return 0
