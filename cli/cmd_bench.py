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
    try:
        from . import cmd_bench_sim
    except ImportError:  # pragma: no cover
        return
    cmd_bench_sim.register(bsub)


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
