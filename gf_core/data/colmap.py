"""Multiview rigs calibrated with COLMAP: a sparse model plus one video per camera.

Layout (a DyNeRF-style capture: each camera's first frame registered with COLMAP, its video beside):
  root/sparse/0/cameras.bin + images.bin   (or cameras.txt + images.txt; also root/sparse/ or root/)
  root/<image stem>.mp4 | .mkv | .mov | .avi   (or under root/videos/): the frames of that camera

Each COLMAP image is one view of the rig; its name's stem (``cam00.png`` -> ``cam00``) names the
video holding that camera's frames, frame k at time k / fps (the video's rate, or ``fps`` given to
``load_dataset``). COLMAP's conventions: the image pose is world-to-camera, ``q`` (w, x, y, z) and
``t`` in OpenCV axes (x right, y down, z forward), and the principal point is in coordinates where
the upper-left pixel's centre is (0.5, 0.5) (``pixel_center`` "half"). Camera models: SIMPLE_PINHOLE
(f, cx, cy), PINHOLE (fx, fy, cx, cy), SIMPLE_RADIAL (f, cx, cy, k), RADIAL (f, cx, cy, k1, k2),
OPENCV (fx, fy, cx, cy, k1, k2, p1, p2), FULL_OPENCV's first eight (k3..k6 must be 0) and
OPENCV_FISHEYE (fx, fy, cx, cy, k1..k4); distortion is removed at load (``distortion``).

The model's world frame is used as it is: COLMAP's own orientation and scale are arbitrary, so a
reconstruction with physics (gravity along -z, sizes in metres) needs a model aligned first
(e.g. ``colmap model_aligner``) or a scene box given in its frame.

The binary and text formats are COLMAP's own (``src/colmap/scene/reconstruction_io.cc``); only the
fields above are read (the 2D points of each image are skipped).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from .dataset import FluidDataset
from .video import video_records

# COLMAP camera model id -> (name, parameter names)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
MODEL_IDS = {name: i for i, (name, _) in CAMERA_MODELS.items()}
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi")


def model_folder(root: Path) -> Path | None:
    """The folder holding the sparse model (cameras + images, .bin or .txt), or None."""
    for d in (root / "sparse" / "0", root / "sparse", root):
        if all((d / f"{n}.bin").exists() for n in ("cameras", "images")) or \
                all((d / f"{n}.txt").exists() for n in ("cameras", "images")):
            return d
    return None


class _Reader:
    """Little-endian fields from a COLMAP binary file; a short file is one clear error."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise InputError(self.path, f"ends inside {what} (truncated file, {len(self.data)} bytes)")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise InputError(self.path, f"ends inside {what}'s name (truncated file)")
        raw, self.pos = self.data[self.pos:end], end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(self.path, f"{what}'s name is not UTF-8") from None


def _camera(model: str, w: int, h: int, params, path: Path, where: str) -> dict:
    p = dict(zip(CAMERA_MODELS[MODEL_IDS[model]][1], (float(v) for v in params)))
    if not all(np.isfinite(list(p.values()))):
        raise InputError(path, f"{where}: non-finite camera parameters {list(p.values())}")
    if w <= 0 or h <= 0:
        raise InputError(path, f"{where}: image size {w}x{h}")
    fx = p.get("fx", p.get("f"))
    fy = p.get("fy", p.get("f"))
    if not (fx > 0 and fy > 0):
        raise InputError(path, f"{where}: focal length {fx}, {fy} is not positive")
    cam = {"w": int(w), "h": int(h), "fl_x": fx, "fl_y": fy, "cx": p["cx"], "cy": p["cy"], "pixel_center": "half"}
    if model == "SIMPLE_RADIAL":
        cam.update(camera_model="OPENCV", k1=p["k"], k2=0.0, p1=0.0, p2=0.0)
    elif model == "RADIAL":
        cam.update(camera_model="OPENCV", k1=p["k1"], k2=p["k2"], p1=0.0, p2=0.0)
    elif model in ("OPENCV", "FULL_OPENCV"):
        if model == "FULL_OPENCV" and any(p[k] != 0.0 for k in ("k3", "k4", "k5", "k6")):
            raise InputError(path, f"{where}: FULL_OPENCV with k3..k6 not zero (the rational model) is not "
                                   "supported; calibrate with OPENCV")
        cam.update(camera_model="OPENCV", **{k: p[k] for k in ("k1", "k2", "p1", "p2")})
    elif model == "OPENCV_FISHEYE":
        cam.update(camera_model="OPENCV_FISHEYE", **{k: p[k] for k in ("k1", "k2", "k3", "k4")})
    return cam


def read_cameras(folder: Path) -> dict[int, dict]:
    """{camera id: camera entry (``video`` layout keys: w, h, fl_x, fl_y, cx, cy, camera_model, k...)}."""
    out = {}
    path = folder / "cameras.bin"
    if path.exists():
        r = _Reader(path)
        (n,) = r.take("Q", "the camera count")
        for k in range(n):
            cid, mid, w, h = r.take("iiQQ", f"camera {k}")
            if mid not in CAMERA_MODELS:
                raise InputError(path, f"camera {cid}: model id {mid} is not one of "
                                       f"{', '.join(f'{i} {m}' for i, (m, _) in CAMERA_MODELS.items())}")
            model, names = CAMERA_MODELS[mid]
            params = r.take("d" * len(names), f"camera {cid}'s parameters")
            out[cid] = _camera(model, w, h, params, path, f"camera {cid}")
        return out
    path = folder / "cameras.txt"
    for ln, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        f = line.split()
        try:
            cid, model, w, h, params = int(f[0]), f[1], int(f[2]), int(f[3]), [float(v) for v in f[4:]]
        except (ValueError, IndexError):
            raise InputError(path, f"line {ln}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {line[:80]!r}") \
                from None
        if model not in MODEL_IDS:
            raise InputError(path, f"line {ln}: camera model {model!r} is not one of {', '.join(MODEL_IDS)}")
        want = len(CAMERA_MODELS[MODEL_IDS[model]][1])
        if len(params) != want:
            raise InputError(path, f"line {ln}: {model} has {want} parameters, got {len(params)}")
        out[cid] = _camera(model, w, h, params, path, f"camera {cid}")
    return out


def read_images(folder: Path) -> list[dict]:
    """[{name, camera_id, world_to_camera (4, 4) OpenCV}] in the file's order."""
    out = []
    path = folder / "images.bin"
    if path.exists():
        r = _Reader(path)
        (n,) = r.take("Q", "the image count")
        for k in range(n):
            vals = r.take("i" + "d" * 7 + "i", f"image {k}")
            name = r.name(f"image {vals[0]}")
            (npts,) = r.take("Q", f"image {name}'s point count")
            r.take("ddq" * npts, f"image {name}'s points")  # x, y, point3D id: not needed
            out.append(_image(vals[0], vals[1:5], vals[5:8], vals[8], name, path))
        return out
    path = folder / "images.txt"
    lines = [ln for ln in enumerate(path.read_text(errors="replace").splitlines(), 1)
             if not ln[1].lstrip().startswith("#")]
    # two lines per image: the pose, then its 2D points (possibly empty)
    for i in range(0, len(lines), 2):
        ln, line = lines[i]
        if not line.strip():
            continue
        f = line.split()
        try:
            iid, q, t, cid, name = int(f[0]), [float(v) for v in f[1:5]], [float(v) for v in f[5:8]], int(f[8]), f[9]
        except (ValueError, IndexError):
            raise InputError(path, f"line {ln}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
                                   f"got {line[:80]!r}") from None
        out.append(_image(iid, q, t, cid, name, path))
    return out


def _image(iid, q, t, cid, name, path) -> dict:
    q, t = np.asarray(q, np.float64), np.asarray(t, np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and norm > 1e-8):
        raise InputError(path, f"image {name!r}: pose q {q.tolist()} t {t.tolist()} is not a rotation and a translation")
    w, x, y, z = q / norm
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    return {"id": int(iid), "name": str(name), "camera_id": int(cid), "world_to_camera": m}


def camera_entries(root: Path) -> list[dict]:
    """The ``video`` layout's camera entries (``cameras.json`` keys) of a COLMAP rig, sorted by
    image name, each with its ``video`` (relative to root) and ``view_id`` (its rank)."""
    folder = model_folder(root)
    if folder is None:
        raise InputError(root, "no COLMAP model (sparse/0/, sparse/ or the folder itself with cameras.bin + "
                               "images.bin, or cameras.txt + images.txt)")
    cams, images = read_cameras(folder), read_images(folder)
    if not images:
        raise InputError(folder, "the COLMAP model has no images (cameras)")
    entries = []
    for k, im in enumerate(sorted(images, key=lambda im: im["name"])):
        if im["camera_id"] not in cams:
            raise InputError(folder, f"image {im['name']!r} refers to camera {im['camera_id']}, which "
                                     "cameras.bin/txt does not have")
        stem = Path(im["name"]).stem
        found = [d / (stem + s) for d in (root, root / "videos") for s in VIDEO_SUFFIXES if (d / (stem + s)).exists()]
        if not found:
            raise InputError(root, f"no video for COLMAP image {im['name']!r}: looked for {stem}"
                                   f"{{{','.join(VIDEO_SUFFIXES)}}} here and in videos/")
        entries.append(dict(cams[im["camera_id"]], video=str(found[0].relative_to(root)),
                            world_to_camera=im["world_to_camera"].tolist(), view_id=k, name=stem))
    return entries


def load_colmap(root, *, fps: float | None = None, grayscale: bool = False,
                background_removal: str | None = None) -> FluidDataset:
    """The COLMAP rig at ``root``: every camera's video, frame k at k / fps (``fps`` or the video's)."""
    root = Path(root)
    entries = camera_entries(root)
    records = video_records(root, entries, model_folder(root), fps=fps, start_time=0.0,
                            fps_hint="give the frame rate (--fps)")
    ch = 1 if grayscale else 3
    return FluidDataset(frames=records, root=root, channels=ch, background=(0.0,) * ch,
                        background_removal=background_removal, meta={"layout": "colmap"})


def rotation_to_quaternion(m) -> tuple:
    """(w, x, y, z) of a 3x3 rotation matrix (Shepperd's method: the branch of the largest component)."""
    m = np.asarray(m, np.float64)
    tr = np.trace(m)
    cands = [1 + tr, 1 + m[0, 0] - m[1, 1] - m[2, 2], 1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2]]
    k = int(np.argmax(cands))
    s = 2 * np.sqrt(cands[k])
    if k == 0:
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
    else:
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
    return tuple(float(v) for v in q)


def write_rig(folder: Path, cameras, names, *, binary: bool = True, params=None, model: str = "PINHOLE") -> Path:
    """The COLMAP model of a rig of toolkit cameras (``camera.Camera``, pinhole; image k named
    ``names[k]``); ``params`` per camera replaces the PINHOLE parameters (another ``model``)."""
    cams = {k + 1: (model, c.width, c.height, params[k] if params is not None else (c.fx, c.fy, c.cx, c.cy))
            for k, c in enumerate(cameras)}
    images = [(k + 1, rotation_to_quaternion(c.world_to_camera[:3, :3]), tuple(float(v) for v in c.world_to_camera[:3, 3]),
               k + 1, name) for k, (c, name) in enumerate(zip(cameras, names))]
    return write_model(folder, cams, images, binary=binary)


def write_model(folder: Path, cameras: dict[int, tuple], images: list[tuple], *, binary: bool = True) -> Path:
    """A COLMAP sparse model with no 3D points: ``cameras`` {id: (model name, w, h, params)},
    ``images`` [(id, (qw, qx, qy, qz), (tx, ty, tz), camera id, name)]. For tests and exporters."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        with open(folder / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cameras)))
            for cid, (model, w, h, params) in cameras.items():
                f.write(struct.pack("<iiQQ", cid, MODEL_IDS[model], w, h))
                f.write(struct.pack("<" + "d" * len(params), *params))
        with open(folder / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(images)))
            for iid, q, t, cid, name in images:
                f.write(struct.pack("<i" + "d" * 7 + "i", iid, *q, *t, cid))
                f.write(name.encode() + b"\0")
                f.write(struct.pack("<Q", 0))
        for n in ("points3D.bin",):
            (folder / n).write_bytes(struct.pack("<Q", 0))
    else:
        (folder / "cameras.txt").write_text("# Camera list\n" + "".join(
            f"{cid} {model} {w} {h} {' '.join(repr(float(v)) for v in params)}\n"
            for cid, (model, w, h, params) in cameras.items()))
        (folder / "images.txt").write_text("# Image list, two lines per image\n" + "".join(
            f"{iid} {' '.join(repr(float(v)) for v in (*q, *t))} {cid} {name}\n\n" for iid, q, t, cid, name in images))
        (folder / "points3D.txt").write_text("# 3D point list\n")
    return folder
