"""``gf-cli reconstruct DATASET --out RUN``: moving Lagrangian particles from multiview images."""

from __future__ import annotations

import sys
from pathlib import Path

DESCRIPTION = """\
Reconstruct the fluid in DATASET as Gaussian particles that move continuously in time (the
GaussFluids method): canonical particles + per-particle transform features + one shared MLP.

Phases: (1) the canonical frame alone, 3DGS-style, particles started inside the visual hull
carved from the alpha masks; (2) every frame, the time decoder learns the motion while the
density loss rises to 10% of its weight; (3) density, volume and anisotropy weights rise to
their final values. Each phase ends at a plateau of its image loss (after its share of the
preset's schedule if it still improves then, at most phases.limit_factor times that share), at
its share of --iterations when given, or at its share of --time-budget when given. Densify/prune runs within --max-particles, in every phase with the water preset
([densify] phases). The water preset adds,
beyond the paper, per-frame residuals from phase 3 on: pose corrections and base-colour
corrections of every particle at each training frame ([decoder] residuals, color_residuals).

Writes RUN/recon.h5 (the result), RUN/metrics.jsonl (one line per logging step: wall-clock
seconds, iteration, phase, every loss term and weight, training and held-out PSNR, particle
count), and RUN/checkpoint.pt (every train.checkpoint_every iterations, at each phase end and on
Ctrl-C; --resume continues from it). Presets and every config key: gf_core/presets/*.toml.
"""


def register(sub):
    import argparse

    p = sub.add_parser("reconstruct", help="reconstruct moving fluid particles from a multiview dataset",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", type=Path, help="dataset folder (NeRF/D-NeRF, NeuroFluid, video or COLMAP layout)")
    p.add_argument("--out", type=Path, required=True, help="run folder for recon.h5, metrics.jsonl, checkpoint.pt")
    p.add_argument("--preset", default="water", choices=["water", "honey", "smoke"],
                   help="configuration preset (default: water)")
    p.add_argument("--config", type=Path, default=None, help="TOML file overriding preset keys (default: none)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--iterations", type=int, default=None,
                   help="total iterations, split between the phases as their caps (default: the preset's schedule "
                        "of phases.iterations, each phase ending at the plateau of its image loss, at most "
                        "phases.limit_factor x its cap)")
    p.add_argument("--max-particles", type=int, default=None, help="particle budget (default: the preset's)")
    p.add_argument("--init-particles", type=int, default=None, help="particles at the start (default: the preset's)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's, 0)")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="stop training after this many wall-clock seconds and write the result (default: none)")
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoint.pt (default: off)")
    p.add_argument("--force", action="store_true", help="start afresh in a RUN folder that holds a run (default: off)")
    p.add_argument("--grayscale", action="store_true", help="one colour channel (smoke footage; default: off)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--resolution", type=int, default=None, metavar="W",
                      help="train on the images W pixels wide (height in proportion), area-averaged when each frame is "
                           "first decoded, intrinsics scaled (default: the footage's own size)")
    size.add_argument("--downscale", type=float, default=None, metavar="K",
                      help="train on the images K times smaller in each side (default: 1)")
    p.add_argument("--background-removal", choices=["difference", "xor"], default=None,
                   help="grayscale footage: remove the background against each view's first frame (default: none)")
    p.add_argument("--fps", type=float, default=None,
                   help="frame rate, for datasets whose time is normalised to [0, 1] (default: the dataset's)")
    p.add_argument("--duration", type=float, default=None,
                   help="seconds the clip spans, for normalised time (default: the dataset's)")
    p.add_argument("--frames", default=None, metavar="START:END:STEP",
                   help="train on these of the dataset's frame times only (python slice over the sorted times: "
                        "'0:20' the first 20, '::2' every other one; the rest are held out in time for "
                        "evaluate --upsample / predict; default: all)")
    p.add_argument("--scene-box", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="the container, metres, z up; write --scene-box=-1,... when it starts with a minus (default: the "
                        "dataset's scene_box, else guessed from the cameras, with no floor)")
    p.add_argument("--floor", type=str, default=None, metavar="Z",
                   help="the floor's height alone, metres (a tank or a table whose walls are unknown; --floor=-0.1 when "
                        "negative; default: the scene box's or the dataset's floor)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: off)")
    p.set_defaults(func=run)


def parse_scene_box(text: str) -> list:
    """``--scene-box X0,Y0,Z0,X1,Y1,Z1`` as [[x0, y0, z0], [x1, y1, z1]]; a bad value names the option."""
    import math

    from gf_core.errors import InputError

    parts = [p.strip() for p in str(text).split(",")]
    try:
        v = [float(p) for p in parts]
    except ValueError:
        v = None
    if v is None or len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise InputError("--scene-box", f"expected six finite numbers X0,Y0,Z0,X1,Y1,Z1 (metres), got {text!r}")
    if not all(v[i + 3] > v[i] for i in range(3)):
        raise InputError("--scene-box", f"each maximum must exceed its minimum (X1 > X0, Y1 > Y0, Z1 > Z0), got {text!r}")
    return [v[:3], v[3:]]


def parse_floor(text: str) -> float:
    """``--floor Z`` as a finite number of metres."""
    import math

    from gf_core.errors import InputError

    try:
        z = float(text)
    except ValueError:
        z = math.nan
    if not math.isfinite(z):
        raise InputError("--floor", f"expected the floor's height as one finite number (metres), got {text!r}")
    return z


def run(args) -> int:
    from tqdm import tqdm

    from gf_core.data import has_split, load_dataset
    from gf_core.errors import InputError
    from gf_core.recon.config import make_config
    from gf_core.recon.trainer import CHECKPOINT, reconstruct

    from .options import check_device

    device = check_device(args.device)
    over = {}
    if args.iterations is not None:
        if args.iterations < 1:
            raise InputError("--iterations", f"must be >= 1, got {args.iterations}")
        # the iterations asked for, exactly: the caps end the phases (no run past them while improving)
        over.setdefault("phases", {}).update(iterations=args.iterations, limit_factor=1.0)
    for opt, key in ((args.max_particles, "max_particles"), (args.init_particles, "init_particles")):
        if opt is not None:
            if opt < 1:
                raise InputError(f"--{key.replace('_', '-')}", f"must be >= 1, got {opt}")
            over.setdefault("model", {})[key] = opt
    if args.max_particles is not None and args.init_particles is None:
        over["model"]["init_particles"] = min(args.max_particles, make_config(args.preset, args.config).model.init_particles)
    if args.seed is not None:
        from gf_core.limits import check_seed

        over.setdefault("train", {})["seed"] = check_seed("--seed", args.seed)
    for opt, v in (("--fps", args.fps), ("--duration", args.duration)):
        if v is not None and not (0 < v < float("inf")):
            raise InputError(opt, f"must be a positive finite number, got {v}")
    if args.time_budget is not None:
        if not args.time_budget > 0:
            raise InputError("--time-budget", f"must be a positive number of seconds, got {args.time_budget}")
        over.setdefault("train", {})["time_budget_s"] = float(args.time_budget)
    if args.scene_box is not None and args.floor is not None:
        raise InputError("--floor", "give --scene-box or --floor, not both (the box's lowest z is its floor)")
    if args.scene_box is not None:
        over.setdefault("model", {}).update(scene_box=parse_scene_box(args.scene_box), floor=[])
    if args.floor is not None:
        over.setdefault("model", {}).update(floor=[parse_floor(args.floor)], scene_box=[])
    cfg = make_config(args.preset, args.config, over)
    out = args.out
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out must be a folder, and this is a file")
    held = [p for p in (out / "recon.h5", out / CHECKPOINT) if p.exists()]
    if held and not args.resume:
        if not args.force:
            raise InputError(out, "already holds a run (recon.h5 or checkpoint.pt); --resume continues it, "
                                  "--force starts afresh")
        for p in held + [out / "metrics.jsonl"]:
            p.unlink(missing_ok=True)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise InputError(out, f"cannot write the run folder ({e.strerror})") from None
    kw = dict(grayscale=args.grayscale, background_removal=args.background_removal, fps=args.fps,
              duration=args.duration, resolution=args.resolution, downscale=args.downscale)
    from .options import parse_frames

    frames = parse_frames(args.frames) if args.frames is not None else None
    train = load_dataset(args.dataset, **kw)
    test = None
    if has_split(args.dataset, "test"):
        test = load_dataset(args.dataset, split="test", **kw)
    if frames is not None:  # the held-out views are scored at the training times
        train = train.select_times(frames)
        test = test.with_times(train.times) if test is not None else None
    if device == "cpu":
        from gf_core.limits import require_memory
        from gf_core.recon.config import training_bytes

        require_memory("--max-particles", f"{cfg.model.max_particles} particles over {len(train.times)} frames "
                                          "(parameters, gradients, optimiser state)",
                       training_bytes(cfg, len(train.times)))
    print(f"dataset {args.dataset}: {len(train)} training images ({len(train.views)} views x {len(train.times)} "
          f"times){f', {len(test)} held-out' if test else ''}; preset {args.preset}, "
          + (f"{cfg.train.time_budget_s:g} s" if cfg.train.time_budget_s > 0 else
             f"{cfg.phases.iterations} iterations" if cfg.phases.limit_factor <= 1 else
             f"{cfg.phases.iterations} iterations or more to each phase's plateau "
             f"(at most {round(cfg.phases.limit_factor * cfg.phases.iterations)})")
          + f", device {device}", flush=True)
    most = cfg.phases.iterations * (cfg.phases.limit_factor if cfg.train.time_budget_s <= 0 else 1)
    bar = None if args.quiet else tqdm(total=round(most), unit="it", file=sys.stderr, dynamic_ncols=True)

    def progress(line):
        if bar is None:
            return
        bar.n = min(line["iteration"], bar.total)
        post = {"phase": line["phase"], "loss": f"{line['loss']:.4f}", "psnr": f"{line['train_psnr']:.2f}",
                "N": line["particles"]}
        if "test_psnr" in line:
            post["test"] = f"{line['test_psnr']:.2f}"
        bar.set_postfix(post, refresh=False)
        bar.refresh()

    def log(msg):
        (bar.write if bar is not None else print)(msg)

    try:
        metrics = reconstruct(train, out, cfg, test_dataset=test, device=device, resume=args.resume, log=log,
                              progress=progress)
    finally:
        if bar is not None:
            bar.close()
    print(f"done: {metrics['particles']} particles, {metrics['iterations']} iterations, {metrics['wall_s']:.1f} s"
          + (f", held-out PSNR {metrics['test_psnr']:.2f} dB" if metrics.get("test_psnr") else "")
          + f" -> {out / 'recon.h5'}")
    return 0
