"""``gf-cli inspect PATH``: summarise a dataset folder, a sim.h5 or a recon.h5 (and validate it)."""

from __future__ import annotations

import json
from pathlib import Path

from gf_core.data import LAYOUTS


def register(sub):
    p = sub.add_parser("inspect", help="validate and summarise a dataset, sim.h5 or recon.h5",
                       description="Validate and summarise a dataset folder (any supported layout), "
                                   "a sim.h5 or a recon.h5. Exits with an error that names the file "
                                   "and the problem if anything is malformed.")
    p.add_argument("path", type=Path, help="a dataset folder, a sim.h5 or a recon.h5")
    p.add_argument("--split", default="train", help="dataset split (default: train)")
    p.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS],
                   help="dataset layout (default: auto-detected)")
    p.add_argument("--grayscale", action="store_true", help="keep one channel (default: off)")
    p.add_argument("--decode", action="store_true",
                   help="also decode every image (full check; default: headers, the ground truth and "
                        "each video's last frame only)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (default: a table)")
    p.set_defaults(func=run)


def summarise(path: Path, args) -> dict:
    from gf_core.errors import InputError

    if not path.exists():
        raise InputError(path, "does not exist")
    if path.is_dir():
        from gf_core.data import load_dataset

        ds = load_dataset(path, layout=args.layout, split=args.split, grayscale=args.grayscale)
        cams = ds.cameras()
        first = next(iter(cams.values()))
        info = {"kind": "dataset", "layout": ds.meta.get("layout"), "frames": len(ds),
                "views": ds.views, "times": len(ds.times), "time_range": list(ds.time_range),
                "channels": ds.channels, "resolution": [first.width, first.height],
                "ground_truth": str(ds.gt_file) if ds.gt_file else None}
        if ds.gt_file is not None:  # the ground truth is read and validated, not only found
            from gf_core.formats.hdf5 import read_sim

            gt = read_sim(ds.gt_file)
            info["ground_truth"] = f"{ds.gt_file} ({gt.num_particles} particles, {gt.num_frames} frames)"
        videos = {}
        for i, fr in enumerate(ds.frames):
            if fr.frame_index is not None and fr.frame_index >= videos.get(fr.file, (-1, 0))[0]:
                videos[fr.file] = (fr.frame_index, i)
        for path, (last, i) in videos.items():  # a truncated video fails on its last frame
            ds.load(i)
        if args.decode:
            for i in range(len(ds)):
                ds.load(i)
            info["decoded"] = len(ds)
        return info
    import h5py

    from gf_core.errors import FormatError
    from gf_core.formats.hdf5 import RECON_FORMAT, SIM_FORMAT, file_format, read_recon, read_sim

    try:
        with h5py.File(path, "r"):
            pass
    except OSError as e:
        raise FormatError(path, f"not a dataset folder nor a readable HDF5 file ({e})") from None
    fmt = file_format(path)
    if fmt == SIM_FORMAT:
        s = read_sim(path)
        return {"kind": "sim", "complete": s.complete, "scene": s.scene, "solver": s.solver, "frames": s.num_frames,
                "particles": s.num_particles, "fps": s.fps, "particle_radius": s.particle_radius,
                "rest_density": s.rest_density, "viscosity": s.viscosity,
                "domain": [list(s.domain_min), list(s.domain_max)]}
    if fmt == RECON_FORMAT:
        r = read_recon(path)
        return {"kind": "recon", "particles": r.num_particles, "sh_degree": r.sh_degree,
                "channels": r.channels, "dynamic": r.decoder is not None,
                "residuals": [name for name, on in (("pose", r.decoder is not None and r.decoder.residuals is not None),
                                                    ("color", r.decoder is not None and
                                                     r.decoder.color_residuals is not None),
                                                    ("opacity", r.decoder is not None and
                                                     r.decoder.opacity_residuals is not None)) if on],
                "time_range": [r.time_min, r.time_max], "metrics": r.metrics}
    raise FormatError(path, f"unknown format {fmt!r} (expected {SIM_FORMAT} or {RECON_FORMAT})")


def run(args) -> int:
    info = summarise(args.path, args)
    if args.json:
        print(json.dumps(info, indent=1))
    else:
        for k, v in info.items():
            print(f"{k:>14}: {v}")
    return 0
