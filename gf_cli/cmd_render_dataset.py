"""``gf-cli render-dataset sim.h5 --out DATASET``: render a multiview dataset with Blender.

Runs render_data/render_dataset.py with a ``blender`` binary (``--blender PATH`` or on PATH),
otherwise with the ``bpy`` module from PyPI, in a separate process. A smoke density grid
(``gf-cli simulate smoke_plume``) is ray-marched in-process instead (``gf_core.data.writers.write_smoke_dataset``).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

from gf_core.errors import GFError, InputError

PASS_THROUGH = ("views", "test_views", "resolution", "samples", "seed", "frames", "material", "fov",
                "threads", "arc", "elevation", "blob", "time_format")
OPTIONAL = ("test_elevation", "transmission")  # passed on only when given


def register(sub):
    p = sub.add_parser("render-dataset", help="render a multiview training dataset from sim.h5 with Blender",
                       description="Render RGBA images of a simulation from N frontal cameras with Cycles "
                                   "(CPU), plus transforms_{train,test}.json, a copy of the particles and a "
                                   "manifest. Uses a blender binary when given or on PATH, otherwise the bpy "
                                   "module. Resumable: re-running skips frames already rendered.")
    p.add_argument("sim", type=Path, help="the simulation (sim.h5, or a smoke plume's grid.h5: ray-marched, grayscale)")
    p.add_argument("--out", type=Path, required=True, help="dataset folder")
    p.add_argument("--views", type=int, default=5, help="training cameras on a frontal arc (default 5)")
    p.add_argument("--test-views", type=int, default=0, help="held-out cameras between them (default 0)")
    p.add_argument("--resolution", type=int, default=400, help="image width and height in pixels (default 400)")
    p.add_argument("--samples", type=int, default=32,
                   help="Cycles samples per pixel (default 32); the images' noise falls as 1/samples "
                        "(scripts/render_noise.py measures it between two seeds)")
    p.add_argument("--denoise", action="store_true", help="denoise (needs a Blender with OpenImageDenoise; default off)")
    p.add_argument("--seed", type=int, default=0, help="render seed (default 0)")
    p.add_argument("--frames", default=":", help="START:END:STEP over the simulation's frames (default: all)")
    p.add_argument("--material", default="auto", choices=["auto", "water", "honey", "smoke"],
                   help="fluid material (default auto: honey for honey scenes, else water)")
    p.add_argument("--fov", type=float, default=40.0, help="horizontal field of view in degrees (default 40)")
    p.add_argument("--show-container", action="store_true", help="let cameras see the tank (default off)")
    p.add_argument("--threads", type=int, default=0, help="render threads (default 0: all)")
    p.add_argument("--arc", type=float, default=90.0, help="degrees the training cameras span (default 90)")
    p.add_argument("--elevation", type=float, default=15.0, help="training cameras' elevation, degrees (default 15)")
    p.add_argument("--test-elevation", type=float, default=None,
                   help="held-out cameras' elevation, degrees (default: the training cameras')")
    p.add_argument("--blob", type=float, default=2.5,
                   help="liquid surface: spheres of this many particle radii around the particles (default 2.5)")
    p.add_argument("--transmission", type=float, default=None,
                   help="water: a principled surface with this transmission weight in [0, 1] instead of clear glass "
                        "(default: glass)")
    p.add_argument("--no-scene-box", action="store_true",
                   help="leave the container out of the transforms files, as real footage comes (default: written)")
    p.add_argument("--time-format", default="seconds", choices=["seconds", "dnerf"],
                   help="frame times in seconds, or D-NeRF's 'time' in [0, 1] with the seconds in 'time_s' "
                        "(default seconds)")
    p.add_argument("--blender", type=Path, default=None, help="a blender executable (default: PATH, else bpy)")
    p.add_argument("--force", action="store_true",
                   help="start afresh when OUT holds a dataset of another simulation or other options (default: refuse)")
    p.set_defaults(func=run)


def script_path() -> Path:
    import render_data

    return Path(render_data.__file__).resolve().parent / "render_dataset.py"


def build_command(args) -> tuple[list[str], str]:
    """(command, engine). Converts sim.h5 to .npz for a blender binary (no h5py needed there)."""
    from gf_core.formats.hdf5 import read_sim

    sim = read_sim(args.sim)  # validates the file before any rendering starts
    opts = []
    for k in PASS_THROUGH:
        opts += [f"--{k.replace('_', '-')}", str(getattr(args, k))]
    for k in OPTIONAL:
        if getattr(args, k, None) is not None:
            opts += [f"--{k.replace('_', '-')}", str(getattr(args, k))]
    if args.denoise:
        opts.append("--denoise")
    if getattr(args, "no_scene_box", False):
        opts.append("--no-scene-box")
    if args.show_container:
        opts.append("--show-container")
    if getattr(args, "force", False):
        opts.append("--force")
    blender = args.blender or (Path(shutil.which("blender")) if shutil.which("blender") else None)
    if blender is not None:
        if not Path(blender).exists():
            raise InputError(blender, "blender executable does not exist")
        from render_data.render_dataset import particles_npz, render_command

        npz, digest = particles_npz(sim, args.sim, args.out)
        cmd = render_command(blender, npz, args.out, digest, opts, blender=True)
        return cmd, "blender"
    if importlib.util.find_spec("bpy") is None:
        raise GFError("render-dataset needs Blender: give --blender PATH, put `blender` on PATH, or "
                      "install the bpy module (pip install 'bpy==5.0.1', Python 3.11; `make setup` does)")
    cmd = [sys.executable, str(script_path()), "--sim", str(args.sim), "--out", str(args.out)] + opts
    return cmd, "bpy"


def check_options(args) -> None:
    """Every option checked before Blender starts."""
    import math

    if args.views < 1:
        raise InputError("--views", f"must be >= 1, got {args.views}")
    if args.test_views < 0:
        raise InputError("--test-views", f"must be >= 0, got {args.test_views}")
    if args.resolution < 8:
        raise InputError("--resolution", f"must be >= 8 pixels, got {args.resolution}")
    if args.resolution > 16384:
        raise InputError("--resolution", f"must be <= 16384 pixels, got {args.resolution}")
    if args.views + args.test_views > 1000:
        raise InputError("--views", f"--views + --test-views must be <= 1000, got {args.views + args.test_views}")
    if args.samples < 1:
        raise InputError("--samples", f"must be >= 1, got {args.samples}")
    if not 0 <= args.seed < 2**31:
        raise InputError("--seed", f"Blender's render seed is an integer in [0, 2^31), got {args.seed}")
    if not (math.isfinite(args.fov) and 0 < args.fov < 180):
        raise InputError("--fov", f"must be an angle in (0, 180) degrees, got {args.fov}")
    if args.threads < 0:
        raise InputError("--threads", f"must be >= 0, got {args.threads}")
    if not 0 < args.arc <= 360:
        raise InputError("--arc", f"must be in (0, 360] degrees, got {args.arc}")
    for flag, v in (("--elevation", args.elevation), ("--test-elevation", args.test_elevation)):
        if v is not None and not -89 <= v <= 89:
            raise InputError(flag, f"must be in [-89, 89] degrees, got {v}")
    if not args.blob > 0:
        raise InputError("--blob", f"must be a positive number of particle radii, got {args.blob}")
    if args.transmission is not None and not 0 <= args.transmission <= 1:
        raise InputError("--transmission", f"must be in [0, 1], got {args.transmission}")
    from .options import parse_frames

    return parse_frames(args.frames)


def check_out(args) -> None:
    """Refuse, before Blender starts, to resume a dataset made from something else (the render
    script checks again, and clears the folder under --force)."""
    import hashlib

    from render_data.render_dataset import IMAGE_OPTIONS, ResumeMismatch, check_resume

    from .options import check_out_dir

    check_out_dir(args.out)
    if getattr(args, "force", False) or not args.out.exists():
        return
    opts = {k: getattr(args, k) for k in IMAGE_OPTIONS}
    ident = {"sim_sha256": hashlib.sha256(Path(args.sim).read_bytes()).hexdigest(), "options": opts}
    try:
        check_resume(args.out, ident, False)
    except ResumeMismatch as e:
        raise InputError(args.out, str(e).split(": ", 1)[1]) from None


def run(args) -> int:
    from gf_core.formats.hdf5 import GRID_FORMAT, file_format, output_lock, read_sim

    frames = check_options(args)
    if file_format(args.sim) == GRID_FORMAT:  # a smoke density grid (gf-cli simulate smoke_plume)
        from gf_core.data.writers import write_smoke_dataset

        from .options import check_out_dir

        check_out_dir(args.out)
        with output_lock(args.out, "dataset"):
            write_smoke_dataset(args.sim, args.out, views=args.views, test_views=args.test_views,
                                 resolution=args.resolution, fov_deg=args.fov, arc_deg=args.arc,
                                 elevation_deg=args.elevation, test_elevation_deg=args.test_elevation, frames=frames)
        print(f"dataset written to {args.out} (ray-marched density, grayscale)", flush=True)
        return 0
    sim = read_sim(args.sim)
    if not range(sim.num_frames)[frames]:
        raise InputError("--frames", f"{args.frames} selects none of the simulation's {sim.num_frames} frames")
    check_out(args)
    with output_lock(args.out, "dataset"):
        return _render(args)


def _render(args) -> int:
    from gf_core.formats.hdf5 import atomic_path

    cmd, engine = build_command(args)
    print(f"rendering with {engine}: {' '.join(cmd[:6])} ...", flush=True)
    proc = subprocess.Popen(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, bufsize=1)
    log = []
    for line in proc.stdout:  # streamed as Blender prints; its per-tile chatter is dropped
        line = line.rstrip("\n")
        log.append(line)
        if line.startswith(("frame ", "dataset written", "Error", "Traceback", "  ")) or "error" in line.lower():
            print(line, flush=True)
    code = proc.wait()
    if code != 0:
        tail = "\n".join(log[-15:])
        raise GFError(f"the render process failed (exit {code}):\n{tail}")
    if engine == "blender":  # Blender's Python has no h5py: the ground-truth copy is made here
        with atomic_path(args.out / "gt_sim.h5") as tmp:
            shutil.copyfile(args.sim, tmp)
    return 0
