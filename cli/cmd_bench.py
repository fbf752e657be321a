"""``gf-cli bench {render,sim}``: figures and ratios, printed as tables and written as JSON."""

from __future__ import annotations

import json
from pathlib import Path


def _ints(s: str) -> list[int]:
    return [int(float(x)) for x in s.split(",") if x]


def register(sub):
    p = sub.add_parser("bench", help="benchmarks: renderer backends, simulators (error vs time)",
                       description="Benchmarks that print tables and write JSON (and plots).")
    bsub = p.add_subparsers(dest="bench", metavar="BENCH")
    bsub.required = True
    r = bsub.add_parser("render", help="renderer backends x particle counts x resolutions",
                        description="Times forward and forward+backward of each renderer backend "
                                    "(median of repeats) and reports the max difference between "
                                    "backends. The scene is documented in gf_core/bench/render_bench.py.")
    r.add_argument("--backends", default="native,reference")
    r.add_argument("--particles", default="1000,20000,50000,200000")
    r.add_argument("--resolutions", default="128,256,400,800")
    r.add_argument("--repeats", type=int, default=5)
    r.add_argument("--device", default="cpu")
    r.add_argument("--reference-max-work", type=float, default=1.2e10,
                   help="skip the reference backend above particles x pixels (default 1.2e10)")
    r.add_argument("--out", type=Path, default=Path("bench_render.json"))
    r.set_defaults(func=run_render)
    q = bsub.add_parser("sim", help="simulators: error vs run time over accuracy sweeps; stability suite",
                        description="Runs DFSPH and PBF over a sweep of accuracy settings (CFL factor "
                                    "and tolerance; substep and iterations) and particle counts, measures "
                                    "the density error itself after every step, energy and wall time, "
                                    "and writes JSON and a PNG of error vs seconds. --stability also runs "
                                    "the stability suite.")
    q.add_argument("--solvers", default="dfsph,pbf")
    q.add_argument("--particles", default="1000,4000")
    q.add_argument("--scene", default="dam_break")
    q.add_argument("--seconds", type=float, default=0.5)
    q.add_argument("--device", default="cpu")
    q.add_argument("--stability", action="store_true", help="also run the stability suite")
    q.add_argument("--out", type=Path, default=Path("bench_sim"), help="output folder (JSON + PNG)")
    q.set_defaults(func=run_sim)


def run_render(args) -> int:
    from gf_core.bench.common import machine, table
    from gf_core.bench.render_bench import bench_render
    from gf_core.io import atomic_write_text

    backends = [b for b in args.backends.split(",") if b]
    for b in backends:
        if b not in ("native", "reference"):
            raise SystemExit(f"gf-cli bench render: unknown backend {b!r} (native, reference)")
    recs = bench_render(backends, _ints(args.particles), _ints(args.resolutions), repeats=args.repeats,
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
    from gf_core.io import atomic_write_text

    solvers = [s for s in args.solvers.split(",") if s]
    for s in solvers:
        if s not in ("dfsph", "pbf"):
            raise SystemExit(f"gf-cli bench sim: unknown solver {s!r} (dfsph, pbf)")
    args.out.mkdir(parents=True, exist_ok=True)
    recs, traces = bench_sim(solvers, _ints(args.particles), scene=args.scene, seconds=args.seconds,
                             device=args.device)
    print()
    print(table(recs, [("solver", "solver", "s"), ("setting", "setting", "s"), ("particles", "N", "d"),
                       ("steps", "steps", "d"), ("wall_s", "wall s", ".1f"),
                       ("wall_per_sim_s", "s per sim s", ".1f"), ("density_err_mean", "mean rho err", ".2e"),
                       ("density_err_max", "max rho err", ".2e"), ("energy_change_rel", "dE/E0", "+.3f")]))
    out = {"machine": machine(), "records": recs, "traces": traces}
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
    plot(recs, traces, args.out / "error_vs_time.png")
    atomic_write_text(args.out / "bench_sim.json", __import__("json").dumps(out, indent=1))
    print(f"\nwrote {args.out / 'bench_sim.json'} and {args.out / 'error_vs_time.png'}")
    return 0
