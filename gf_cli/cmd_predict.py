"""``gf-cli predict RUN --at T --frames N --out sim.h5``: continue a reconstruction with a simulator
(paper Sec. 4.3.4). The options shared with ``gf-cli edit`` live here too."""

from __future__ import annotations

import sys
from pathlib import Path


def add_continuation_options(p) -> None:
    from gf_core.sim import SOLVERS

    p.add_argument("run", type=Path, help="run folder (holding recon.h5) or a recon.h5 file")
    p.add_argument("--out", type=Path, required=True, help="output sim.h5 (render it with render-dataset, "
                                                           "the Blender extension, or gf-cli evaluate)")
    p.add_argument("--at", type=float, default=None, metavar="T",
                   help="start time in seconds (default: the reconstruction's last training frame)")
    p.add_argument("--frames", type=int, default=40, help="frames to simulate (default 40)")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate of the continuation (default: the dataset's, else 30)")
    p.add_argument("--solver", choices=list(SOLVERS), default="pbf",
                   help="particle solver (default pbf, as in the paper)")
    p.add_argument("--rest-density", type=float, default=1000.0,
                   help="kg/m^3, for the particles' mass and energies (default 1000, water)")
    p.add_argument("--viscosity", type=float, default=0.0, help="kinematic viscosity, m^2/s (default 0)")
    p.add_argument("--velocity", choices=["frames", "analytic"], default="frames",
                   help="starting velocities: finite differences of the decoded positions over a frame interval "
                        "(default), or the decoder's instantaneous time derivative")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: off)")


def load_state(args):
    from gf_core.errors import InputError
    from gf_core.formats.hdf5 import read_recon
    from gf_core.downstream.predict import state_at

    from .options import check_device
    from .options import check_out_file

    check_device(args.device)
    check_out_file(args.out)
    if args.frames < 1:
        raise InputError("--frames", f"must be >= 1, got {args.frames}")
    for name in ("fps", "rest_density"):
        v = getattr(args, name)
        if v is not None and not (v > 0 and v != float("inf")):
            raise InputError(f"--{name.replace('_', '-')}", f"must be a positive number, got {v}")
    if not (args.viscosity >= 0 and args.viscosity != float("inf")):
        raise InputError("--viscosity", f"must be >= 0, got {args.viscosity}")
    recon = args.run / "recon.h5" if args.run.is_dir() else args.run
    if not recon.exists():
        raise InputError(recon, "no reconstruction here (run gf-cli reconstruct first)")
    r = read_recon(recon)
    from gf_core.limits import require_memory

    require_memory("--frames", f"{args.frames} frames of {r.num_particles} particles (positions and velocities)",
                   float(args.frames) * r.num_particles * 24)
    fps = args.fps or r.config.get("fps") or 30.0
    return recon, r, state_at(r, args.at, velocity=args.velocity), float(fps)


def reconstruction_spacing(recon) -> float | None:
    """The mean particle spacing the reconstruction implies: (fluid volume / particle count)^(1/3)."""
    from gf_core.formats.hdf5 import read_recon

    r = read_recon(recon)
    vol = r.config.get("fluid_volume")
    return (float(vol) / r.num_particles) ** (1 / 3) if vol and r.num_particles else None


def simulate_state(args, recon, state, fps, command: str) -> int:
    import time

    from tqdm import tqdm

    from gf_core.downstream.predict import continue_state

    bar = None

    def progress(f, n, t, last):
        nonlocal bar
        if args.quiet:
            return
        if bar is None:
            bar = tqdm(total=n, unit="frame", file=sys.stderr)
        bar.update(1)

    t0 = time.perf_counter()
    try:
        sim, rep = continue_state(state, frames=args.frames, fps=fps, solver=args.solver,
                                  rest_density=args.rest_density, viscosity=args.viscosity, out=args.out,
                                  device=args.device, progress=progress,
                                  config={"command": command, "recon": str(Path(recon).resolve())})
    finally:
        if bar is not None:
            bar.close()
    expected = reconstruction_spacing(recon)
    if expected and not 0.5 < rep["spacing"] / expected < 2.0:
        print(f"warning: the particles' spacing at t = {state.time:.4g} s ({rep['spacing']:.4g} m, from their nearest "
              f"neighbours and density) is far from the reconstruction's own ({expected:.4g} m, its fluid volume / "
              f"particle count): the particles are clumped or torn apart at that time, and the continuation will "
              f"not be a fluid at rest density; try an earlier --at, or a longer reconstruction", file=sys.stderr)
    print(f"{command}: {sim.num_particles} particles from t = {state.time:.4g} s, {sim.num_frames - 1} frames at "
          f"{fps:g} fps with {args.solver} (spacing {rep['spacing']:.4g} m estimated from the particles), "
          f"{rep['steps']} steps in {time.perf_counter() - t0:.1f} s -> {args.out}")
    return 0


def register(sub):
    p = sub.add_parser("predict", help="continue a reconstruction with PBF or DFSPH into a sim.h5",
                       description="Take the reconstructed particles at time T (positions, and velocities from the "
                                   "decoded positions one frame apart), estimate their spacing and rest density from the "
                                   "particles, and simulate N more frames inside the scene box (paper Sec. 4.3.4). "
                                   "The sim.h5 names the reconstruction and keeps, per particle, the index of the "
                                   "Gaussian whose appearance it has: gf-cli evaluate SIM.h5 renders it with the "
                                   "learned appearance and compares with the dataset's frames and ground truth.")
    add_continuation_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    recon, _, state, fps = load_state(args)
    return simulate_state(args, recon, state, fps, "predict")
