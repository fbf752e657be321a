"""Bad input generated from good files: every key of every format the toolkit reads, mutated.

A base scene (a simulation, a rendered NeRF-layout dataset, a video-layout ``cameras.json``, a
reconstruction and its checkpoint) is made once; each case copies the file it mutates into its
own folder, changes one thing (a key missing, of the wrong type, NaN, nested too deep, the file
truncated or not UTF-8) and runs the commands that read it. ``tests/cli/test_reliability.py`` runs the
cases: each either works or ends in one line naming the file, exit code 2, never a traceback.
"""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# replacement values for a JSON / TOML / HDF5 value: (name, value); None = delete the key
JSON_VALUES = [("missing", None), ("string", "x"), ("number", 7), ("nan", float("nan")), ("negative", -1.0),
               ("list", []), ("ragged", [[1, 2], [3]]), ("object", {"a": 1}), ("null", "__null__"),
               ("bool", True), ("huge", 1e308)]


@dataclass
class Case:
    """One bad input: ``make(tmp)`` writes it under ``tmp`` and returns the argv to run."""
    id: str
    make: object
    must_refuse: bool = False     # True: exit code 2 is the only right answer
    tags: list = field(default_factory=list)


# ---- the base scene ----------------------------------------------------------------------------------
def make_base(root: Path) -> dict:
    """A 3-frame falling blob: sim.h5, a 16x16 NeRF dataset (3 + 1 views), a video-layout cameras.json,
    a 30-iteration reconstruction with a decoder and residuals. Seconds on a laptop."""
    from gf_core.data import load_dataset
    from gf_core.formats.hdf5 import write_sim
    from gf_core.recon.config import make_config
    from gf_core.recon.trainer import reconstruct
    from gf_core.synthetic import falling_blob, splat_dataset

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    sim = falling_blob(n_side=5, frames=3)
    write_sim(root / "sim.h5", sim)
    ds = splat_dataset(root / "ds", sim, views=3, test_views=1, resolution=16)
    cfg = make_config("water", overrides={
        "phases": {"iterations": 30, "limit_factor": 1.0}, "model": {"init_particles": 64, "max_particles": 128},
        "decoder": {"hidden_width": 16, "hidden_layers": 1, "feature_dim": 4},
        "train": {"eval_every": 30, "checkpoint_every": 30}})
    reconstruct(load_dataset(ds), root / "run", cfg, log=lambda *a, **k: None)
    (root / "config.toml").write_text(TINY_TOML)
    # a run made by the command itself, whose checkpoint `reconstruct --resume` with the same config reads
    from gf_cli.main import main

    if main(["reconstruct", str(ds), "--out", str(root / "ckrun"), "--config", str(root / "config.toml"), "--quiet"]):
        raise RuntimeError("the base run for the checkpoint cases failed")
    return {"root": root, "sim": root / "sim.h5", "ds": ds, "run": root / "run", "recon": root / "run" / "recon.h5",
            "toml": root / "config.toml", "ckrun": root / "ckrun"}


TINY_TOML = """[model]
init_particles = 64
max_particles = 128
[decoder]
hidden_width = 16
hidden_layers = 1
feature_dim = 4
[phases]
iterations = 2
limit_factor = 1.0
[train]
eval_every = 2
checkpoint_every = 2
log_every = 1
"""


# ---- mutations ---------------------------------------------------------------------------------------
def _json_paths(obj, prefix=()):
    """Every key path of a JSON document (into the first element of each list of objects)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield prefix + (k,)
            yield from _json_paths(v, prefix + (k,))
    elif isinstance(obj, list) and obj and isinstance(obj[0], (dict, list)):
        yield prefix + (0,)
        if isinstance(obj[0], dict):
            yield from _json_paths(obj[0], prefix + (0,))


def _set(obj, path, value):
    for p in path[:-1]:
        obj = obj[p]
    if value is None:
        if isinstance(obj, dict):
            del obj[path[-1]]
        else:
            obj.pop(path[-1])
    else:
        obj[path[-1]] = None if value == "__null__" else value


def json_variants(doc: dict):
    """(name, text or bytes) for every key of ``doc`` and every replacement, plus whole-file damage."""
    for path in _json_paths(doc):
        for name, value in JSON_VALUES:
            d = copy.deepcopy(doc)
            _set(d, path, value)
            yield ".".join(map(str, path)) + "=" + name, json.dumps(d)
    text = json.dumps(doc)
    yield "truncated", text[: len(text) // 2]
    yield "empty", ""
    yield "not-utf8", b"\xff\xfe" + text.encode("utf-16-le")
    yield "deep", "[" * 10000 + "]" * 10000
    yield "top-list", "[1, 2, 3]"
    yield "frames-empty", json.dumps({**doc, "frames": []}) if "frames" in doc else "{}"


def h5_items(path: Path) -> list[tuple[str, str]]:
    """(kind, name) of every dataset and attribute of an HDF5 file (attributes as 'group@attr')."""
    import h5py

    out = []
    with h5py.File(path, "r") as f:
        for k in f.attrs:
            out.append(("attr", "@" + k))

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out.append(("dataset", name))
            for k in obj.attrs:
                out.append(("attr", name + "@" + k))
        f.visititems(visit)
    return out


H5_VALUES = ["missing", "string", "nan", "shape", "empty", "huge"]


def h5_mutate(path: Path, kind: str, name: str, how: str) -> None:
    import h5py

    with h5py.File(path, "r+") as f:
        if kind == "attr":
            grp, attr = name.split("@")
            obj = f[grp] if grp else f
            old = obj.attrs[attr]
            del obj.attrs[attr]
            if how == "missing":
                return
            a = np.asarray(old)
            obj.attrs[attr] = {"string": "six", "nan": np.full(a.shape, np.nan) if a.dtype.kind in "fiub" else "NaN",
                               "shape": np.zeros((2, 2)), "empty": np.zeros(0),
                               "huge": np.full(a.shape, 1e30) if a.dtype.kind in "fiub" else "[" * 5000}[how]
            return
        a = np.asarray(f[name][()])
        del f[name]
        if how == "missing":
            return
        if how == "string":
            f[name] = "not numbers"
        elif how == "nan":
            f[name] = np.full(a.shape, np.nan) if a.dtype.kind == "f" else np.full(a.shape, -1, a.dtype)
        elif how == "shape":
            f[name] = a.reshape(-1)[:-1] if a.size > 1 else np.zeros((2, 2))
        elif how == "empty":
            f[name] = np.zeros((0,) + a.shape[1:], a.dtype)
        elif how == "huge":
            f[name] = np.full(a.shape, 1e30) if a.dtype.kind == "f" else np.full(a.shape, 2 ** 40)


def toml_variants():
    """(name, text) of a tiny reconstruct config with one key of the water preset changed."""
    import tomllib

    from gf_core.recon.config import PRESET_DIR

    preset = tomllib.loads((PRESET_DIR / "water.toml").read_text())
    tiny = tomllib.loads(TINY_TOML)
    values = [("string", '"x"'), ("nan", "nan"), ("inf", "inf"), ("negative", "-1"), ("zero", "0"),
              ("huge", "1e300"), ("big-int", "9223372036854775807"), ("list", "[1, 2]"), ("table", "{a = 1}")]
    for sec, keys in preset.items():
        for key in keys:
            for name, v in values:
                body = {s: dict(k) for s, k in tiny.items()}
                body.setdefault(sec, {})[key] = "__RAW__"
                text = "\n".join(f"[{s}]\n" + "\n".join(
                    f"{k} = {v if val == '__RAW__' else _toml(val)}" for k, val in kv.items()) for s, kv in body.items())
                yield f"{sec}.{key}={name}", text
    yield "truncated", TINY_TOML[: len(TINY_TOML) // 2] + "= ["
    yield "not-utf8", TINY_TOML.encode("utf-16")
    yield "unknown-section", TINY_TOML + "[nope]\na = 1\n"


def _toml(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    return repr(v)


# ---- the cases ---------------------------------------------------------------------------------------
def _copy_ds(base, tmp: Path) -> Path:
    ds = tmp / "ds"
    shutil.copytree(base["ds"], ds)
    return ds


def _copy_run(base, tmp: Path) -> Path:
    run = tmp / "run"
    shutil.copytree(base["run"], run)
    return run


def cases(base: dict) -> list[Case]:
    out: list[Case] = []

    # transforms_train.json: every key, read by inspect (and the same loader in reconstruct/evaluate)
    doc = json.loads((base["ds"] / "transforms_train.json").read_text())
    for name, text in json_variants(doc):
        def make(tmp, text=text):
            ds = _copy_ds(base, tmp)
            p = ds / "transforms_train.json"
            p.write_bytes(text if isinstance(text, bytes) else text.encode())
            return ["inspect", str(ds)]
        whole_file = "=" not in name
        out.append(Case(f"transforms:{name}", make, must_refuse=whole_file, tags=["dataset"]))

    # a torn image: truncated after the dataset was written
    def torn(tmp):
        ds = _copy_ds(base, tmp)
        p = ds / "train" / "v00_f00001.png"
        p.write_bytes(p.read_bytes()[:40])
        return ["inspect", str(ds), "--decode"]
    out.append(Case("image:truncated", torn, must_refuse=True, tags=["dataset"]))

    # video layout: cameras.json (every key), through inspect
    cams = _video_cameras(base)
    for name, text in json_variants(cams):
        def make(tmp, text=text):
            root = _video_dataset(base, tmp)
            (root / "cameras.json").write_bytes(text if isinstance(text, bytes) else text.encode())
            return ["inspect", str(root), "--layout", "video"]
        out.append(Case(f"cameras:{name}", make, must_refuse="=" not in name, tags=["video"]))

    # PINF / HyFluid layout: info.json (every key), through inspect
    for name, text in json_variants(_pinf_info(base)):
        def make(tmp, text=text):
            root = _video_dataset(base, tmp)
            (root / "cameras.json").unlink()
            (root / "info.json").write_bytes(text if isinstance(text, bytes) else text.encode())
            return ["inspect", str(root), "--layout", "pinf"]
        out.append(Case(f"info:{name}", make, must_refuse="=" not in name, tags=["pinf"]))

    # COLMAP rig: the sparse model's binary fields and text tokens, through inspect
    for name, change in colmap_variants():
        def make(tmp, change=change, binary=name.startswith("bin")):
            root = _colmap_dataset(base, tmp, binary=binary)
            change(root / "sparse" / "0")
            return ["inspect", str(root), "--layout", "colmap"]
        out.append(Case(f"colmap:{name}", make, must_refuse="truncated" in name, tags=["colmap"]))

    # sim.h5 through inspect, render-dataset's reader and evaluate --gt
    for kind, item in h5_items(base["sim"]):
        for how in H5_VALUES:
            def make(tmp, kind=kind, item=item, how=how):
                p = tmp / "sim.h5"
                shutil.copy(base["sim"], p)
                h5_mutate(p, kind, item, how)
                return ["inspect", str(p)]
            out.append(Case(f"sim:{item}={how}", make, tags=["sim"]))

    # recon.h5 through inspect, export, predict and evaluate
    commands = [lambda r, t: ["inspect", str(r / "recon.h5")],
                lambda r, t: ["export", str(r), "--format", "ply", "--out", str(t / "x.ply")],
                lambda r, t: ["predict", str(r), "--frames", "2", "--out", str(t / "p.h5"), "--quiet"],
                lambda r, t: ["evaluate", str(r), "--out", str(t / "ev")]]
    for i, (kind, item) in enumerate(h5_items(base["recon"])):
        for j, how in enumerate(H5_VALUES):
            cmd = commands[(i + j) % len(commands)]

            def make(tmp, kind=kind, item=item, how=how, cmd=cmd):
                run = _copy_run(base, tmp)
                h5_mutate(run / "recon.h5", kind, item, how)
                return cmd(run, tmp)
            out.append(Case(f"recon:{item}={how}", make, tags=["recon"]))
    # the keys of recon.h5's config attribute that readers use
    import h5py

    with h5py.File(base["recon"], "r") as f:
        rcfg = json.loads(f.attrs["config"])
    paths = [(k,) for k in rcfg] + [("bounds", k) for k in rcfg.get("bounds", {})]
    for i, path in enumerate(paths):
        for j, (how, value) in enumerate([("string", "x"), ("nan", float("nan")), ("list", [1, 2]), ("null", None),
                                         ("negative", -1.0)]):
            cmd = commands[(i + j) % len(commands)]

            def make(tmp, path=path, value=value, cmd=cmd):
                run = _copy_run(base, tmp)
                with h5py.File(run / "recon.h5", "r+") as f:
                    c = json.loads(f.attrs["config"])
                    d = c
                    for p in path[:-1]:
                        d = d[p]
                    d[path[-1]] = value
                    f.attrs["config"] = json.dumps(c)
                return cmd(run, tmp)
            out.append(Case(f"recon:config.{'.'.join(path)}={how}", make, tags=["recon"]))
    for cmd in commands:
        def make(tmp, cmd=cmd):
            run = _copy_run(base, tmp)
            p = run / "recon.h5"
            p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
            return cmd(run, tmp)
        out.append(Case(f"recon:truncated:{cmd(Path('r'), Path('t'))[0]}", make, must_refuse=True, tags=["recon"]))

    # the checkpoint that `reconstruct --resume` reads: every key, and every per-particle tensor
    for name, change in checkpoint_variants(base["ckrun"] / "checkpoint.pt"):
        def make(tmp, change=change):
            import torch

            run = tmp / "ckrun"
            shutil.copytree(base["ckrun"], run)
            ck = run / "checkpoint.pt"
            st = torch.load(ck, map_location="cpu", weights_only=True)
            change(st)
            torch.save(st, ck)
            return ["reconstruct", str(base["ds"]), "--out", str(run), "--config", str(base["toml"]), "--resume",
                    "--quiet"]
        out.append(Case(f"checkpoint:{name}", make, tags=["checkpoint"]))

    # reconstruct --config: every key of the water preset
    for name, text in toml_variants():
        def make(tmp, text=text):
            p = tmp / "c.toml"
            p.write_bytes(text if isinstance(text, bytes) else text.encode())
            return ["reconstruct", str(base["ds"]), "--out", str(tmp / "r"), "--config", str(p), "--quiet"]
        out.append(Case(f"config:{name}", make, must_refuse=name in ("truncated", "not-utf8", "unknown-section"),
                        tags=["config"]))

    # options: huge, degenerate, out of range
    for argv in OPTION_CASES:
        def make(tmp, argv=argv):
            return [a.format(tmp=tmp, ds=base["ds"], run=base["run"], sim=base["sim"]) for a in argv]
        out.append(Case("option:" + " ".join(argv[:1] + argv[2:]), make, must_refuse=True, tags=["option"]))
    return out


def checkpoint_variants(path: Path):
    """(name, function that changes a loaded checkpoint dict in place) for every top-level key
    (missing, a string, None, NaN) and every per-particle tensor (a row short, NaN, a string)."""
    import torch

    st = torch.load(path, map_location="cpu", weights_only=True)
    out = []
    for key in st:
        if key == "format":
            continue
        for how, value in (("missing", None), ("string", "x"), ("null", "__null__"), ("nan", float("nan"))):
            def change(d, key=key, value=value):
                if value is None:
                    del d[key]
                else:
                    d[key] = None if value == "__null__" else value
            out.append((f"{key}={how}", change))
    for key in st["params"]:
        for how in ("short", "nan", "string"):
            def change(d, key=key, how=how):
                v = d["params"][key]
                d["params"][key] = v[:-1] if how == "short" else (v * float("nan") if how == "nan" else "x")
            out.append((f"params.{key}={how}", change))
    if st.get("mlp"):
        first = next(iter(st["mlp"]))

        def change(d, first=first):
            d["mlp"][first] = d["mlp"][first][:, :-1]
        out.append((f"mlp.{first}=wrong-shape", change))
    return out


OPTION_CASES = [
    ["simulate", "water_cube", "--particles", "1000000000000", "--out", "{tmp}/s.h5"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--init-particles", "4000000000"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--max-particles", "4000000000"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--seed", "-1"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--seed", "99999999999999999999999"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--time-budget", "nan"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--time-budget", "-5"],
    ["reconstruct", "{ds}", "--out", "{tmp}/r", "--fps", "inf"],
    ["reconstruct", "{ds}", "--out", "{sim}"],
    ["edit", "{run}", "--out", "{tmp}/e.h5", "--add-box", "-100", "-100", "-100", "100", "100", "100"],
    ["edit", "{run}", "--out", "{tmp}/e.h5", "--seed", "-3", "--remove-fraction", "0.5"],
    ["edit", "{run}", "--out", "{tmp}/e.h5", "--remove-fraction", "nan"],
    ["edit", "{run}", "--out", "{tmp}/e.h5", "--remove-fraction", "2"],
    ["predict", "{run}", "--out", "{tmp}/p.h5", "--frames", "0"],
    ["predict", "{run}", "--out", "{tmp}/p.h5", "--frames", "100000000000000"],
    ["predict", "{run}", "--out", "{tmp}/p.h5", "--at", "nan"],
    ["predict", "{run}", "--out", "{tmp}/p.h5", "--viscosity", "-1"],
    ["export", "{run}", "--format", "vdb", "--voxel", "1e-7", "--out", "{tmp}/v"],
    ["export", "{run}", "--format", "vdb", "--voxel", "nan", "--out", "{tmp}/v"],
    ["export", "{run}", "--format", "ply", "--fps", "0", "--out", "{tmp}/v"],
    ["export", "{run}", "--format", "ply", "--time", "inf", "--out", "{tmp}/x.ply"],
    ["evaluate", "{run}", "--out", "{sim}"],
    ["evaluate", "{run}", "--upsample", "0", "--out", "{tmp}/ev"],
    ["render-dataset", "{sim}", "--out", "{tmp}/d", "--seed", "99999999999"],
    ["render-dataset", "{sim}", "--out", "{tmp}/d", "--resolution", "1000000"],
    ["render-dataset", "{sim}", "--out", "{tmp}/d", "--views", "0"],
    ["render-dataset", "{sim}", "--out", "{tmp}/d", "--samples", "0"],
    ["render-dataset", "{sim}", "--out", "{sim}"],
]


# COLMAP binary fields: (file, name, byte offset of the first camera / image record's field, struct format, value)
COLMAP_FIELDS = [
    ("cameras.bin", "count-huge", 0, "<Q", 2 ** 40), ("cameras.bin", "count-zero", 0, "<Q", 0),
    ("cameras.bin", "model-unknown", 12, "<i", 99), ("cameras.bin", "model-negative", 12, "<i", -3),
    ("cameras.bin", "width-zero", 16, "<Q", 0), ("cameras.bin", "height-huge", 24, "<Q", 2 ** 62),
    ("cameras.bin", "fx-nan", 32, "<d", float("nan")), ("cameras.bin", "fx-negative", 32, "<d", -20.0),
    ("cameras.bin", "cx-inf", 48, "<d", float("inf")),
    ("images.bin", "count-huge", 0, "<Q", 2 ** 40), ("images.bin", "count-zero", 0, "<Q", 0),
    ("images.bin", "q-zero", 12, "<dddd", (0.0, 0.0, 0.0, 0.0)), ("images.bin", "q-nan", 12, "<d", float("nan")),
    ("images.bin", "t-inf", 44, "<d", float("inf")), ("images.bin", "camera-unknown", 68, "<i", 99),
    ("images.bin", "name-not-utf8", 72, "<BB", (0xFF, 0xFE)),
]


def colmap_variants():
    """(name, change(model folder)) for the binary model's fields and truncations and the text
    model's every token (wrong, NaN, missing, an extra one) and line."""
    import struct

    for fname, name, off, fmt, value in COLMAP_FIELDS:
        def change(folder, fname=fname, off=off, fmt=fmt, value=value):
            p = folder / fname
            data = bytearray(p.read_bytes())
            struct.pack_into(fmt, data, off, *(value if isinstance(value, tuple) else (value,)))
            p.write_bytes(bytes(data))
        yield f"bin:{fname}:{name}", change
    for fname in ("cameras.bin", "images.bin"):
        for frac in (0.0, 0.05, 0.3, 0.6, 0.95):
            def change(folder, fname=fname, frac=frac):
                p = folder / fname
                data = p.read_bytes()
                p.write_bytes(data[: int(len(data) * frac)])
            yield f"bin:{fname}:truncated{frac}", change
    # text: the first camera line has 8 tokens (id model w h fx fy cx cy), the first image line 10
    for fname, tokens in (("cameras.txt", 8), ("images.txt", 10)):
        for k in range(tokens):
            for how, repl in (("word", "x"), ("nan", "nan"), ("negative", "-1"), ("missing", None)):
                def change(folder, fname=fname, k=k, repl=repl):
                    p = folder / fname
                    lines = p.read_text().splitlines()
                    i = next(j for j, ln in enumerate(lines) if ln and not ln.startswith("#"))
                    toks = lines[i].split()
                    if repl is None:
                        del toks[k]
                    else:
                        toks[k] = repl
                    lines[i] = " ".join(toks)
                    p.write_text("\n".join(lines) + "\n")
                yield f"txt:{fname}:token{k}={how}", change
        for how in ("empty", "extra-token", "not-utf8"):
            def change(folder, fname=fname, how=how):
                p = folder / fname
                if how == "empty":
                    p.write_text("")
                elif how == "not-utf8":
                    p.write_bytes(b"\xff\xfe" + p.read_text().encode("utf-16-le"))
                else:
                    lines = p.read_text().splitlines()
                    i = next(j for j, ln in enumerate(lines) if ln and not ln.startswith("#"))
                    lines[i] += " 3.5"
                    p.write_text("\n".join(lines) + "\n")
            yield f"txt:{fname}:{how}", change


def _colmap_dataset(base, tmp: Path, binary: bool) -> Path:
    """The video layout's videos beside a COLMAP model of its cameras (no cameras.json)."""
    from gf_core.data import load_dataset
    from gf_core.data.colmap import write_rig

    root = _video_dataset(base, tmp)
    ds = load_dataset(root, layout="video")
    cams = {f.view_id: f.camera for f in ds.frames}
    (root / "cameras.json").unlink()
    write_rig(root / "sparse" / "0", [cams[v] for v in sorted(cams)], [f"view{v}.png" for v in sorted(cams)],
              binary=binary)
    return root


def _video_cameras(base) -> dict:
    doc = json.loads((base["ds"] / "transforms_train.json").read_text())
    views = {}
    for fr in doc["frames"]:
        views.setdefault(fr["view_id"], fr)
    return {"fps": doc["fps"], "cameras": [
        {"video": f"view{v}.mkv", "transform_matrix": fr["transform_matrix"], "fl_x": fr["fl_x"], "fl_y": fr["fl_y"],
         "cx": fr["cx"], "cy": fr["cy"]} for v, fr in sorted(views.items())]}


def _pinf_info(base) -> dict:
    """The video layout's cameras as a PINF / HyFluid info.json (frame_num and camera_hw from the videos)."""
    import math

    cams = _video_cameras(base)
    doc = json.loads((base["ds"] / "transforms_train.json").read_text())
    w, h = doc["frames"][0].get("w", 16), doc["frames"][0].get("h", 16)
    n = len({fr["time"] for fr in doc["frames"]})
    videos = [{"file_name": c["video"], "frame_rate": cams["fps"], "frame_num": n, "camera_hw": [h, w],
               "camera_angle_x": 2 * math.atan(0.5 * w / c["fl_x"]), "transform_matrix": c["transform_matrix"]}
              for c in cams["cameras"]]
    return {"train_videos": videos[:-1], "test_videos": videos[-1:], "frame_bkg_color": [0.0, 0.0, 0.0],
            "voxel_matrix": [[1, 0, 0, -0.5], [0, 1, 0, -0.5], [0, 0, 1, 0], [0, 0, 0, 1]], "voxel_scale": [1, 1, 1],
            "rot": "Z"}


def _video_dataset(base, tmp: Path) -> Path:
    """The base dataset as a video layout: one FFV1 video (.mkv) per training view (made once, then copied)."""
    cache = base["root"] / "video"
    if not cache.exists():
        from gf_core.data.images import read_image, to_float
        from gf_core.data.videos import write_video

        doc = json.loads((base["ds"] / "transforms_train.json").read_text())
        tmp_cache = base["root"] / "video.tmp"
        tmp_cache.mkdir(exist_ok=True)
        for v in sorted({fr["view_id"] for fr in doc["frames"]}):
            frames = [(to_float(read_image(base["ds"] / fr["file_path"]))[..., :3] * 255).round().astype(np.uint8)
                      for fr in doc["frames"] if fr["view_id"] == v]
            write_video(tmp_cache / f"view{v}.mkv", frames, fps=10.0)
        (tmp_cache / "cameras.json").write_text(json.dumps(_video_cameras(base)))
        tmp_cache.rename(cache)
    root = tmp / "video"
    shutil.copytree(cache, root)
    return root


__all__ = ["Case", "make_base", "cases"]
