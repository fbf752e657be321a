"""``gf-cli demo``: the main job on the built-in scene, end to end with what exists so far.

1. simulate the built-in scene (water_sphere, DFSPH)               -> OUT/sim.h5
2. render a 5-view dataset of it with Blender (Cycles, CPU)          -> OUT/dataset/
3. load the dataset back and splat the ground-truth particles as Gaussians into every view with
   the differentiable renderer; report the alpha agreement with Blender's masks
4. write a contact sheet: Blender renders above, Gaussian splats below -> OUT/contact_sheet.png
Reconstruction (``gf-cli reconstruct``) slots in between 3 and 4 once it exists.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def register(sub):
    p = sub.add_parser("demo", help="run the main job on the built-in scene (simulate, render, splat)",
                       description=__doc__.split("\n\n")[0] + " Steps: simulate the water_sphere scene, "
                       "render a 5-view dataset with Blender, load it back, splat the particles with the "
                       "Gaussian renderer and compare with Blender's masks, write a contact sheet.")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--particles", type=int, default=1500, help="approximate particle count (default 1500)")
    p.add_argument("--seconds", type=float, default=0.5, help="simulated seconds (default 0.5)")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second (default 20)")
    p.add_argument("--resolution", type=int, default=128, help="image size in pixels (default 128)")
    p.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    import torch

    from gf_core.data import load_dataset
    from gf_core.data.images import write_png
    from gf_core.io import atomic_write_text, write_sim
    from gf_core.particles import GaussianParticles
    from gf_core.sim import simulate

    from . import cmd_render_dataset

    import importlib.util
    import shutil
    import sys

    from gf_core.errors import GFError, InputError

    # everything the demo needs, checked before the simulation starts
    if importlib.util.find_spec("bpy") is None and shutil.which("blender") is None:
        raise GFError(f"the demo renders with Blender: install the bpy module (pip install 'bpy==5.0.1', which needs "
                      f"Python 3.11; this is Python {sys.version.split()[0]}) or put `blender` on PATH")
    for name in ("particles", "resolution", "samples"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name}", f"must be >= 1, got {getattr(args, name)}")
    for name in ("seconds", "fps"):
        if not getattr(args, name) > 0:
            raise InputError(f"--{name}", f"must be a positive number, got {getattr(args, name)}")
    out = args.out
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out must be a folder, and this is a file")
    out.mkdir(parents=True, exist_ok=True)
    report = {}
    t0 = time.perf_counter()
    sim, res = simulate("water_sphere", particles=args.particles, fps=args.fps, seconds=args.seconds)
    write_sim(out / "sim.h5", sim)
    report["simulate"] = {"particles": sim.num_particles, "frames": sim.num_frames,
                          "seconds": round(time.perf_counter() - t0, 2),
                          "final_density_error": float(sim.stats["density_err_mean"][-1])}
    print(f"[1/4] simulated {sim.num_particles} particles, {sim.num_frames} frames "
          f"in {report['simulate']['seconds']} s -> {out / 'sim.h5'}")

    t0 = time.perf_counter()
    rargs = argparse.Namespace(sim=out / "sim.h5", out=out / "dataset", views=5, test_views=0,
                               resolution=args.resolution, samples=args.samples, denoise=False, seed=0,
                               frames="::2", material="water", fov=40.0, show_container=False,
                               threads=0, blender=None)
    cmd_render_dataset.run(rargs)
    report["render"] = {"seconds": round(time.perf_counter() - t0, 2)}
    print(f"[2/4] rendered the dataset in {report['render']['seconds']} s -> {out / 'dataset'}")

    ds = load_dataset(out / "dataset")
    print(f"[3/4] loaded {len(ds)} images ({len(ds.views)} views x {len(ds.times)} times); splatting "
          "the ground-truth particles into each view")
    ious, tops, bottoms = [], [], []
    for t_idx, t in enumerate(ds.times):
        frame = int(np.argmin(np.abs(sim.times - t)))
        gp = GaussianParticles.from_positions(sim.positions[frame], radius=sim.particle_radius,
                                              color=(0.55, 0.75, 1.0), opacity=0.6)
        for view in ds.views:
            s = ds[ds.indices(view_id=view, time=t)[0]]
            with torch.no_grad():
                o = gp.render(s.camera, background=torch.ones(3))
            a_ref, a_gs = s.alpha.numpy() > 0.5, o.alpha.numpy() > 0.5
            union = np.logical_or(a_ref, a_gs).sum()
            ious.append(float(np.logical_and(a_ref, a_gs).sum() / max(union, 1)))
            if t_idx == len(ds.times) // 2:
                tops.append(s.composite(torch.ones(3)).numpy())
                bottoms.append(o.color.numpy())
    report["splat_vs_blender_alpha_iou"] = {"mean": float(np.mean(ious)), "min": float(np.min(ious))}
    sheet = np.concatenate([np.concatenate(tops, 1), np.concatenate(bottoms, 1)], 0)
    write_png(out / "contact_sheet.png", np.clip(sheet, 0, 1))
    atomic_write_text(out / "demo_report.json", json.dumps(report, indent=1))
    print(f"[4/4] alpha IoU of the Gaussian splats vs Blender's masks: mean "
          f"{report['splat_vs_blender_alpha_iou']['mean']:.3f}; contact sheet -> {out / 'contact_sheet.png'}")
    return 0
