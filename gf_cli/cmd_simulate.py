"""``gf-cli simulate SCENE --out sim.h5``: run a preset scene with DFSPH or PBF."""

from __future__ import annotations

import sys
import time
from pathlib import Path


def register(sub):
    from gf_core.sim import SCENES, SOLVERS

    p = sub.add_parser("simulate", help="simulate a preset scene (DFSPH or PBF) into sim.h5",
                       description="Simulate a preset scene and write sim.h5 (positions and velocities "
                                   "per frame, the solver's settings and per-frame density error and "
                                   f"energy). Scenes: {', '.join(SCENES)}.")
    p.add_argument("scene", choices=[*SCENES, "smoke_plume"],
                   help="a particle scene, or smoke_plume: a rising smoke plume on a grid (stable fluids), "
                        "written as a density grid per frame (grid.h5) for gf-cli render-dataset")
    p.add_argument("--out", type=Path, required=True, help="output sim.h5")
    p.add_argument("--solver", choices=list(SOLVERS), default="dfsph", help="particle solver (default: dfsph)")
    p.add_argument("--particles", type=int, default=2000, help="approximate particle count (default 2000)")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the scene's, 60)")
    p.add_argument("--seconds", type=float, default=None, help="simulated time (default: the scene's)")
    p.add_argument("--settle", type=float, default=None, metavar="S",
                   help="seconds of damped settling before t = 0, from which the fluid starts at rest "
                        "(default: the scene's; hydrostatic_tank 6, others 0)")
    p.add_argument("--viscosity", type=float, default=None, metavar="NU",
                   help="kinematic viscosity in m^2/s, solved implicitly (default: the scene material's)")
    p.add_argument("--viscosity-boundary", choices=("free-slip", "no-slip"), default=None,
                   help="whether the viscosity also acts against the walls (no-slip) or not (free-slip); default: "
                        "the material's (water free-slip, honey no-slip)")
    p.add_argument("--backend", choices=("auto", "native", "torch"), default="auto",
                   help="the solver's pair sums: native C++ (CPU), the torch reference, or auto (native where built)")
    p.add_argument("--cells", type=int, default=48, help="smoke_plume: cells along the domain's longest side (default 48)")
    p.add_argument("--seed", type=int, default=0, help="smoke_plume: the source noise's seed (default 0)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: off)")
    p.set_defaults(func=run)


def check_options(args) -> None:
    from gf_core.errors import InputError

    for name in ("fps", "seconds"):
        v = getattr(args, name)
        if v is not None and not (v > 0 and v != float("inf")):
            raise InputError(f"--{name}", f"must be a positive number, got {v}")
    if args.settle is not None and not (args.settle >= 0 and args.settle != float("inf")):
        raise InputError("--settle", f"must be >= 0 seconds, got {args.settle}")
    if args.particles is not None and args.particles < 1:
        raise InputError("--particles", f"must be >= 1, got {args.particles}")
    if args.particles is not None:
        from gf_core.limits import PARTICLE_BYTES, require_memory

        require_memory("--particles", f"{args.particles} particles", float(args.particles) * PARTICLE_BYTES)
    if args.viscosity is not None and not (args.viscosity >= 0 and args.viscosity != float("inf")):
        raise InputError("--viscosity", f"must be >= 0 m^2/s, got {args.viscosity}")
    from .options import check_device, check_out_file

    check_device(args.device)
    check_out_file(args.out)


def _overrides(args) -> dict:
    """Solver settings given on the command line (the rest come from the scene)."""
    out = {}
    if args.viscosity_boundary is not None:
        out["viscosity_boundary"] = args.viscosity_boundary
    if args.viscosity is not None:
        out["viscosity"] = args.viscosity
    if args.backend != "auto":
        out["backend"] = args.backend
    return out


def _smoke(args) -> int:
    from gf_core.errors import InputError
    from gf_core.formats.hdf5 import output_lock, write_grid
    from gf_core.limits import check_seed
    from gf_core.sim.smoke import PlumeConfig, simulate_plume

    if not 8 <= args.cells <= 512:
        raise InputError("--cells", f"must be in [8, 512], got {args.cells}")
    cfg = PlumeConfig(cells=args.cells, seed=check_seed("--seed", args.seed),
                      **{k: v for k, v in (("fps", args.fps), ("seconds", args.seconds)) if v is not None})
    t0 = time.perf_counter()
    with output_lock(args.out, "simulation"):
        g = simulate_plume(cfg)
        write_grid(args.out, g)
    print(f"smoke_plume: {'x'.join(map(str, g.density.shape[1:]))} cells, {g.density.shape[0]} frames at "
          f"{g.fps:g} fps in {time.perf_counter() - t0:.1f} s -> {args.out}")
    return 0


def run(args) -> int:
    from tqdm import tqdm

    from gf_core.formats.hdf5 import output_lock
    from gf_core.sim import simulate

    check_options(args)  # before the (possibly long) settle and simulation
    if args.scene == "smoke_plume":
        return _smoke(args)

    bar = None
    t0 = time.perf_counter()

    def progress(f, n, t, last):
        nonlocal bar
        if args.quiet:
            return
        if bar is None:
            bar = tqdm(total=n, unit="frame", file=sys.stderr)
        bar.set_postfix(t=f"{t:.3f}s", dt=f"{last.get('dt', 0):.1e}",
                        rho_err=f"{100 * last.get('density_err_mean', 0):.3f}%")
        bar.update(1)

    try:
        with output_lock(args.out, "simulation"):
            sim, res = simulate(args.scene, solver=args.solver, particles=args.particles, fps=args.fps,
                                seconds=args.seconds, device=args.device, progress=progress,
                                settle_seconds=args.settle, out=args.out,  # written frame by frame
                                **_overrides(args))
    except KeyboardInterrupt:
        if bar:
            bar.close()
        if args.out.exists():
            print(f"interrupted: the frames computed so far are in {args.out} (marked incomplete); the same "
                  "command again goes on from its last frame", file=sys.stderr)
        raise
    if bar:
        bar.close()
    wall = time.perf_counter() - t0
    print(f"{args.scene} ({args.solver}): {sim.num_particles} particles, {sim.num_frames} frames at "
          f"{sim.fps:g} fps, {len(res.steps)} steps in {wall:.1f} s; final mean density error "
          f"{100 * sim.stats['density_err_mean'][-1]:.3f}% -> {args.out}"
          + (f" (resumed after frame {sim.config['resumed_after_frame']})" if "resumed_after_frame" in sim.config else ""))
    return 0
