"""``gf-cli render-dataset sim.h5 --out DATASET``: render a multiview dataset with Blender.

Runs render_data/render_dataset.py with a ``blender`` binary (``--blender PATH`` or on PATH),
otherwise with the ``bpy`` module from PyPI, in a separate process.
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
                "threads")


def register(sub):
    p = sub.add_parser("render-dataset", help="render a multiview training dataset from sim.h5 with Blender",
                       description="Render RGBA images of a simulation from N frontal cameras with Cycles "
                                   "(CPU), plus transforms_{train,test}.json, a copy of the particles and a "
                                   "manifest. Uses a blender binary when given or on PATH, otherwise the bpy "
                                   "module. Resumable: re-running skips frames already rendered.")
    p.add_argument("sim", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--views", type=int, default=5)
    p.add_argument("--test-views", type=int, default=0)
    p.add_argument("--resolution", type=int, default=400)
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--denoise", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", default=":", help="START:END:STEP over the simulation's frames")
    p.add_argument("--material", default="auto", choices=["auto", "water", "honey", "smoke"])
    p.add_argument("--fov", type=float, default=40.0)
    p.add_argument("--show-container", action="store_true")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--blender", type=Path, default=None, help="a blender executable (default: PATH, else bpy)")
    p.set_defaults(func=run)


def script_path() -> Path:
    import render_data

    return Path(render_data.__file__).resolve().parent / "render_dataset.py"


def build_command(args) -> tuple[list[str], str]:
    """(command, engine). Converts sim.h5 to .npz for a blender binary (no h5py needed there)."""
    from gf_core.io import read_sim

    sim = read_sim(args.sim)  # validates the file before any rendering starts
    opts = []
    for k in PASS_THROUGH:
        opts += [f"--{k.replace('_', '-')}", str(getattr(args, k))]
    if args.denoise:
        opts.append("--denoise")
    if args.show_container:
        opts.append("--show-container")
    blender = args.blender or (Path(shutil.which("blender")) if shutil.which("blender") else None)
    if blender is not None:
        if not Path(blender).exists():
            raise InputError(blender, "blender executable does not exist")
        import numpy as np

        args.out.mkdir(parents=True, exist_ok=True)
        npz = args.out / ".gf_particles.npz"
        np.savez(npz, positions=sim.positions, times=sim.times, fps=sim.fps,
                 particle_radius=sim.particle_radius, domain_min=np.asarray(sim.domain_min),
                 domain_max=np.asarray(sim.domain_max), scene=sim.scene, rest_density=sim.rest_density,
                 gt_file="gt_sim.h5")
        shutil.copyfile(args.sim, args.out / "gt_sim.h5")
        cmd = [str(blender), "-b", "--factory-startup", "-noaudio", "-P", str(script_path()), "--",
               "--sim", str(npz), "--out", str(args.out)] + opts
        return cmd, "blender"
    if importlib.util.find_spec("bpy") is None:
        raise GFError("render-dataset needs Blender: give --blender PATH, put `blender` on PATH, or "
                      "install the bpy module (pip install 'bpy==5.0.1', Python 3.11; `make setup` does)")
    cmd = [sys.executable, str(script_path()), "--sim", str(args.sim), "--out", str(args.out)] + opts
    return cmd, "bpy"


def run(args) -> int:
    cmd, engine = build_command(args)
    print(f"rendering with {engine}: {' '.join(cmd[:6])} ...", flush=True)
    proc = subprocess.run(cmd, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    log = proc.stdout.splitlines()
    for line in log:  # Blender's own per-tile chatter is dropped; our progress lines are kept
        if line.startswith(("frame ", "dataset written", "Error", "Traceback", "  ")) or "error" in line.lower():
            print(line)
    if proc.returncode != 0:
        tail = "\n".join(log[-15:])
        raise GFError(f"the render process failed (exit {proc.returncode}):\n{tail}")
    return 0
