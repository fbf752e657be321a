"""Render a multiview training dataset from a simulation, headless.

    blender -b -P render_data/render_dataset.py -- --sim sim.h5 --out DATASET [options]
    python render_data/render_dataset.py --sim sim.h5 --out DATASET [options]   (bpy module)

Writes DATASET/{train,test}/v{view}_f{frame}.png (RGBA), transforms_{train,test}.json (NeRF
layout: camera-to-world in Blender's convention, camera_angle_x, per-frame time in seconds,
view_id), gt_sim.h5 (a copy of the simulation) and manifest.json (options, Blender version).
Deterministic under --seed; resumable: frames whose images all exist are skipped, and images
are written under a temporary name and renamed, so a killed run never leaves a partial PNG.
Needs bpy + numpy, and h5py for a .h5 input (a .npz input needs nothing else).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

SIM_FORMAT, SIM_VERSION = "gaussfluids.sim", 1
H5PY_HELP = ("h5py is not importable in this Blender's Python, so {path} cannot be read. Either run "
             "through `gf-cli render-dataset` (it hands Blender the particles as .npz), install the "
             "GaussFluids Blender extension (it bundles h5py), or install h5py into Blender's Python: "
             "`<blender>/<version>/python/bin/python3.11 -m pip install h5py`.")


def parse_args(argv):
    p = argparse.ArgumentParser(prog="render_dataset.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--sim", required=True, help="sim.h5 (needs h5py) or a .npz written by gf-cli")
    p.add_argument("--out", required=True, help="output dataset folder")
    p.add_argument("--views", type=int, default=5, help="training cameras on a frontal arc (default 5)")
    p.add_argument("--test-views", type=int, default=0, help="held-out cameras between them")
    p.add_argument("--resolution", type=int, default=400)
    p.add_argument("--samples", type=int, default=32, help="Cycles samples per pixel")
    p.add_argument("--denoise", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", default=":", help="START:END:STEP over the simulation's frames (python slice)")
    p.add_argument("--material", default="auto", choices=["auto", "water", "honey", "smoke"])
    p.add_argument("--fov", type=float, default=40.0, help="horizontal field of view, degrees")
    p.add_argument("--show-container", action="store_true",
                   help="let cameras see the tank and floor (default: only reflections/refractions)")
    p.add_argument("--threads", type=int, default=0, help="render threads (0: all)")
    p.add_argument("--arc", type=float, default=90.0, help="degrees the training cameras span around the scene")
    p.add_argument("--elevation", type=float, default=15.0, help="training cameras' elevation, degrees")
    p.add_argument("--test-elevation", type=float, default=None,
                   help="held-out cameras' elevation, degrees (default: the training cameras')")
    p.add_argument("--blob", type=float, default=2.5,
                   help="particle-to-surface radius, in particle radii (the mesh of a liquid is the surface of "
                        "spheres this large around the particles)")
    p.add_argument("--transmission", type=float, default=None,
                   help="water only: a principled surface with this transmission weight in [0, 1] instead of "
                        "clear glass")
    p.add_argument("--no-scene-box", action="store_true",
                   help="leave the container out of the transforms files, as real footage comes")
    p.add_argument("--time-format", default="seconds", choices=["seconds", "dnerf"],
                   help="'seconds': frame time in seconds; 'dnerf': 'time' normalised to [0, 1] over the clip with "
                        "the seconds in 'time_s' and no 'fps' (as D-NeRF exports write it)")
    p.add_argument("--force", action="store_true",
                   help="start afresh when OUT holds a dataset of another simulation or other options")
    p.add_argument("--source-hash", default=None,
                   help="sha256 of the original sim.h5 (gf-cli passes it when it hands over a .npz)")
    a = p.parse_args(argv)
    if a.views < 1 or a.test_views < 0 or a.resolution < 8 or a.samples < 1:
        p.error("need views >= 1, test-views >= 0, resolution >= 8, samples >= 1")
    if not 0 < a.arc <= 360 or not -89 <= a.elevation <= 89 or \
            (a.test_elevation is not None and not -89 <= a.test_elevation <= 89):
        p.error("need 0 < arc <= 360 and elevations in [-89, 89] degrees")
    if not a.blob > 0 or (a.transmission is not None and not 0 <= a.transmission <= 1):
        p.error("need blob > 0 and transmission in [0, 1]")
    return a


def _attr(f, name):
    v = f.attrs[name]
    return v.decode() if isinstance(v, bytes) else v


def load_particles(path: str) -> dict:
    """positions (F, N, 3), times (F,), fps, particle_radius, domain, scene, rest_density."""
    p = Path(path)
    if not p.exists():
        raise SystemExit(f"{p}: file does not exist")
    if p.suffix == ".npz":
        with np.load(p, allow_pickle=False) as d:
            out = {k: d[k] for k in d.files}
        out = {k: (v.item() if v.shape == () else v) for k, v in out.items()}
    else:
        try:
            import h5py
        except ImportError:
            raise SystemExit(H5PY_HELP.format(path=p)) from None
        try:
            f = h5py.File(p, "r")
        except OSError as e:
            raise SystemExit(f"{p}: not a readable HDF5 file ({e})") from None
        with f:
            if _attr(f, "format") != SIM_FORMAT or int(f.attrs.get("version", -1)) != SIM_VERSION:
                raise SystemExit(f"{p}: not a {SIM_FORMAT} v{SIM_VERSION} file")
            out = {"positions": f["positions"][()], "times": f["times"][()], "fps": float(f.attrs["fps"]),
                   "particle_radius": float(f.attrs["particle_radius"]),
                   "domain_min": np.asarray(f.attrs["domain_min"]), "domain_max": np.asarray(f.attrs["domain_max"]),
                   "scene": str(_attr(f, "scene")), "rest_density": float(f.attrs["rest_density"])}
    pos = np.asarray(out["positions"], np.float32)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[1] == 0:
        raise SystemExit(f"{p}: positions must be (frames, particles >= 1, 3), got {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise SystemExit(f"{p}: positions contain NaN or infinite values")
    out["positions"] = pos
    return out


def png_ok(path: Path, size: int) -> bool:
    """A complete PNG of ``size`` x ``size``: the signature, the size in its header, every chunk
    whole with a matching CRC, and the closing IEND chunk (a file torn by a full disk or an
    interrupted copy fails; such a frame is rendered again)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return False
    if len(data) < 24 or data[:8] != b"\x89PNG\r\n\x1a\n" or struct.unpack(">II", data[16:24]) != (size, size):
        return False
    i = 8
    while i + 12 <= len(data):
        n = struct.unpack(">I", data[i:i + 4])[0]
        end = i + 12 + n
        if end > len(data) or zlib.crc32(data[i + 4:i + 8 + n]) != struct.unpack(">I", data[i + 8 + n:end])[0]:
            return False
        if data[i + 4:i + 8] == b"IEND":
            return True
        i = end
    return False


IDENTITY_FILE = "render_source.json"
IMAGE_OPTIONS = ("views", "test_views", "resolution", "samples", "seed", "material", "fov", "show_container",
                 "denoise", "arc", "elevation", "test_elevation", "blob", "transmission")


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def source_identity(a) -> dict:
    """What the images are made from: the simulation's bytes and every option that changes a pixel
    (the frame range is not one: a resumed run may render more frames)."""
    return {"sim_sha256": a.source_hash or file_sha256(a.sim),
            "options": {k: getattr(a, k) for k in IMAGE_OPTIONS}}


class ResumeMismatch(Exception):
    """OUT holds a dataset made from another simulation or other options."""


def check_resume(out: Path, ident: dict, force: bool) -> bool:
    """Refuse to mix runs: OUT may only be resumed by the same simulation and options. Returns
    True when OUT starts afresh (nothing there, or cleared by --force)."""
    idf = out / IDENTITY_FILE
    has_images = any(out.glob("train/*.png")) or any(out.glob("test/*.png"))
    if idf.exists():
        try:
            old = json.loads(idf.read_text())
        except json.JSONDecodeError:
            old = {}
    elif has_images:
        old = {"sim_sha256": "unknown (no render_source.json)", "options": {}}
    else:
        return True
    if old == ident:
        return False
    why = []
    if old.get("sim_sha256") != ident["sim_sha256"]:
        why.append(f"the simulation differs (sha256 {str(old.get('sim_sha256'))[:12]}.. here, "
                   f"{ident['sim_sha256'][:12]}.. given)")
    for k, v in ident["options"].items():
        if k in old.get("options", {}) and old["options"][k] != v:
            why.append(f"--{k.replace('_', '-')} {old['options'][k]} here, {v} given")
    if not force:
        raise ResumeMismatch(f"{out}: holds a dataset made from something else ({'; '.join(why) or 'unknown source'}); "
                             "use --force to start afresh or choose another --out")
    for sub in ("train", "test"):
        shutil.rmtree(out / sub, ignore_errors=True)
    for name in ("transforms_train.json", "transforms_test.json", "manifest.json", "gt_sim.h5", IDENTITY_FILE):
        (out / name).unlink(missing_ok=True)
    print(f"--force: cleared {out} ({'; '.join(why)})", flush=True)
    return True


def particles_npz(sim, sim_path, out: Path) -> tuple[Path, str]:
    """Hand a simulation to a Python without h5py (a Blender binary): write OUT/.gf_particles.npz
    from ``sim`` (a validated ``gf_core.formats.hdf5.SimData``) and return it with the sha256 of ``sim_path``,
    which the render script records as the dataset's source (``--source-hash``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    npz = out / ".gf_particles.npz"
    np.savez(npz, positions=sim.positions, times=sim.times, fps=sim.fps,
             particle_radius=sim.particle_radius, domain_min=np.asarray(sim.domain_min),
             domain_max=np.asarray(sim.domain_max), scene=sim.scene, rest_density=sim.rest_density,
             gt_file="gt_sim.h5")
    return npz, file_sha256(sim_path)


def render_command(python_or_blender, npz: Path, out: Path, digest: str, opts: list, *, blender: bool) -> list:
    """The command that renders ``npz`` into ``out``: a Blender binary runs this script with -P,
    a Python with the bpy module runs it directly."""
    script = str(Path(__file__).resolve())
    args = ["--sim", str(npz), "--out", str(out), "--source-hash", digest] + [str(o) for o in opts]
    if blender:
        return [str(python_or_blender), "-b", "--factory-startup", "-noaudio", "-P", script, "--"] + args
    return [str(python_or_blender), script] + args


def write_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    a = parse_args(argv)
    sim = load_particles(a.sim)
    import bpy

    import scene_builder as sb

    material = a.material
    if material == "auto":
        material = "honey" if ("honey" in str(sim.get("scene", "")) or sim.get("rest_density", 1000) > 1200) else "water"
    frames = list(range(sim["positions"].shape[0]))[slice(*[int(x) if x else None for x in a.frames.split(":")])]
    if not frames:
        raise SystemExit(f"--frames {a.frames} selects no frame of {sim['positions'].shape[0]}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ident = source_identity(a)
    try:
        fresh = check_resume(out, ident, a.force)
    except ResumeMismatch as e:
        raise SystemExit(str(e)) from None
    write_json(out / IDENTITY_FILE, ident)
    fluid, cams, tcams = sb.build_scene(
        n_particles=sim["positions"].shape[1], radius=float(sim["particle_radius"]), material=material,
        domain_min=sim["domain_min"], domain_max=sim["domain_max"], views=a.views, test_views=a.test_views,
        resolution=a.resolution, samples=a.samples, seed=a.seed, denoise=a.denoise, fov_deg=a.fov,
        show_container=a.show_container, threads=a.threads, arc_deg=a.arc, elevation_deg=a.elevation,
        test_elevation_deg=a.test_elevation, blob=a.blob, transmission=a.transmission)
    splits = [("train", cams)] + ([("test", tcams)] if tcams else [])
    for split, _ in splits:
        (out / split).mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    for k, fi in enumerate(frames):
        jobs = [(cam, out / split / f"v{v:02d}_f{fi:05d}.png")
                for split, cs in splits for v, cam in enumerate(cs)]
        todo = [(c, p) for c, p in jobs if not png_ok(p, a.resolution)]
        if not todo:
            print(f"frame {k + 1}/{len(frames)} (sim frame {fi}): already rendered, skipped", flush=True)
            continue
        t0 = time.perf_counter()
        sb.set_particles(fluid, sim["positions"][fi])
        for cam, path in todo:
            tmp = path.with_name(path.stem + ".partial.png")
            sb.render_to(str(tmp), cam)
            os.replace(tmp, path)
        print(f"frame {k + 1}/{len(frames)} (sim frame {fi}, t = {float(sim['times'][fi]):.3f} s): "
              f"{len(todo)} images in {time.perf_counter() - t0:.1f} s", flush=True)
    gt_name = None
    if Path(a.sim).suffix != ".npz":
        gt_name = "gt_sim.h5"
        if fresh or not (out / gt_name).exists():  # resumes check the identity, so a kept copy is the same
            shutil.copyfile(a.sim, out / (gt_name + ".partial"))
            os.replace(out / (gt_name + ".partial"), out / gt_name)
    elif sim.get("gt_file"):
        gt_name = str(sim["gt_file"])
    cam0 = cams[0].data
    for split, cs in splits:
        entries = []
        for fi in frames:
            for v, cam in enumerate(cs):
                # held-out cameras are numbered after the training ones: ids name cameras, not slots
                t = float(sim["times"][fi])
                e = {"file_path": f"{split}/v{v:02d}_f{fi:05d}.png",
                     "view_id": v + (len(cams) if split == "test" else 0),
                     "camera_name": cam.name, "time": t, "frame": int(fi),
                     "transform_matrix": [list(map(float, row)) for row in cam.matrix_world]}
                if a.time_format == "dnerf":  # [0, 1] over the rendered clip, seconds beside it
                    t0, t1 = float(sim["times"][frames[0]]), float(sim["times"][frames[-1]])
                    e.update(time=(t - t0) / (t1 - t0) if t1 > t0 else 0.0, time_s=t)
                    del e["frame"]
                entries.append(e)
        meta = {"camera_angle_x": float(cam0.angle_x), "w": a.resolution, "h": a.resolution,
                "fps": float(sim["fps"]), "time_unit": "seconds", "background": [0.0, 0.0, 0.0],
                "scene_box": [list(map(float, sim["domain_min"])), list(map(float, sim["domain_max"]))],
                "frames": entries}
        if a.time_format == "dnerf":
            del meta["fps"], meta["time_unit"]
        if a.no_scene_box:
            del meta["scene_box"]
        if gt_name:
            meta["gt_particles"] = gt_name
        write_json(out / f"transforms_{split}.json", meta)
    manifest = {"generator": "gaussfluids render_data/render_dataset.py", "blender": bpy.app.version_string,
                "options": vars(a), "source": ident, "material": material, "frames": frames,
                "particles": int(sim["positions"].shape[1]), "scene": str(sim.get("scene", "")),
                "render_seconds": time.perf_counter() - t_start}
    write_json(out / "manifest.json", manifest)
    print(f"dataset written to {out} ({len(frames)} frames x {len(cams)} views"
          f"{f' + {len(tcams)} test views' if tcams else ''})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
