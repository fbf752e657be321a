"""Exports of a reconstruction for other tools (paper Sec. 4.3; ``gf-cli export``).

- ``ply``: the Gaussians at one time as a 3DGS PLY (binary little-endian; the properties common
  3DGS viewers read: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3, with the
  activations 3DGS expects: logit opacity, log scales, quaternion w x y z, SH coefficients with
  f_rest channel-major). Grayscale reconstructions are written with their channel in all three.
  The SH are written at degree 3 by default (``sh_degree``), higher coefficients zero: the
  reference 3DGS reader (``GaussianModel.load_ply``) and most viewers expect exactly 45 f_rest
  properties and refuse or misread others; a lower degree drops the coefficients above it.
- ``gltf``: the Gaussians at one time as binary glTF 2.0 (``.glb``) with the Khronos
  ``KHR_gaussian_splatting`` extension: a POINTS primitive with POSITION, ``:SCALE`` (log),
  ``:ROTATION`` (unit quaternion x y z w), ``:OPACITY`` (in [0, 1]), ``:SH_DEGREE_l_COEF_n`` (RGB,
  every coefficient of the model's degree), COLOR_0 (base colour and opacity, for viewers that
  draw plain points); kernel ellipse, colour space srgb_rec709_display. The node turns the
  toolkit's z-up world into glTF's y-up.
- ``particles``: per frame a PLY of points: x y z vx vy vz radius opacity (velocities from the
  decoder's time derivative, m/s).
- ``vtk``: per frame a legacy VTK file (an unstructured grid of vertex cells, binary) of the same points, with ``velocity``
  as a 3-vector and ``radius``, ``opacity`` as scalars: what meshio-based loaders (Blender's
  sequence loader, ParaView) read as a ``velocity`` vector attribute (motion blur), which no PLY
  reader gives (PLY properties are scalars).
- ``vdb``: per frame an OpenVDB float grid ``density``, class fog volume (``gf_core.caches``).
- ``usd``: one USD file of points with time samples: positions, widths, velocities, and the
  base colour and opacity of every point as ``displayColor`` / ``displayOpacity`` (``gf_core.caches``).

Times: by default the reconstruction's training frames (``frame_times_s`` in recon.h5), else a
grid at ``fps`` over the clip; ``--fps`` resamples the clip (the decoder is continuous).
Numpy only (the decoder is ``gf_core.decoder_np``); pxr/openvdb for usd/vdb.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .decoder_np import ParticleAnimation
from .errors import FormatError, InputError
from .io import atomic_path

FORMATS = ("ply", "gltf", "particles", "vtk", "vdb", "usd")
GLTF_EXTENSION = "KHR_gaussian_splatting"


# ---- PLY (binary little-endian, float32 properties) ------------------------------------------------
def write_ply(path, columns: dict) -> Path:
    """A vertex element whose float32 properties are ``columns`` (name -> (N,) array), in order."""
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    data = np.empty((n, len(names)), "<f4")
    for k, name in enumerate(names):
        col = np.asarray(columns[name], np.float32)
        if col.shape != (n,):
            raise ValueError(f"PLY column {name} has shape {col.shape}, expected ({n},)")
        data[:, k] = col
    header = ["ply", "format binary_little_endian 1.0", "comment GaussFluids", f"element vertex {n}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(data.tobytes())
    return path


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
              "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4"}


def read_ply(path) -> dict:
    """The vertex element of a binary little-endian PLY as {property: (N,) array}."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise FormatError(path, "not a PLY file (no 'ply' magic or no end_header)")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in [ln.strip() for ln in lines]:
        raise FormatError(path, "only binary little-endian PLY files are read")
    fields, n, in_vertex, offset = [], None, False, 0
    for ln in lines:
        parts = ln.split()
        if parts[:1] == ["element"]:
            if in_vertex:
                break  # the vertex element comes first in every file we read
            in_vertex = parts[1] == "vertex"
            if not in_vertex:
                raise FormatError(path, f"expected the vertex element first, got {parts[1]!r}")
            n = int(parts[2])
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise FormatError(path, f"unsupported property {' '.join(parts[1:])!r}")
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None:
        raise FormatError(path, "no vertex element")
    dt = np.dtype(fields)
    if len(raw) - body_start < n * dt.itemsize:
        raise FormatError(path, f"truncated: {n} vertices need {n * dt.itemsize} bytes, "
                                f"{len(raw) - body_start} present")
    arr = np.frombuffer(raw, dt, count=n, offset=body_start)
    return {name: arr[name].copy() for name, _ in fields}


# ---- 3DGS layout --------------------------------------------------------------------------------
SH_DEGREES = (0, 1, 2, 3)


def gaussians_to_ply_columns(means, log_scales, quats, logit_opacity, sh, *, sh_degree: int | None = 3) -> dict:
    """3DGS PLY columns; ``sh`` (N, K, 1 or 3) written at ``sh_degree`` (zeros above the model's
    degree, coefficients above ``sh_degree`` dropped; None = the model's own degree)."""
    n, k, c = sh.shape
    if c == 1:  # grayscale: the same coefficients in R, G and B
        sh = np.repeat(sh, 3, axis=2)
    if sh_degree is not None:
        if sh_degree not in SH_DEGREES:
            raise InputError("--sh-degree", f"must be one of {', '.join(map(str, SH_DEGREES))}, got {sh_degree}")
        want = (sh_degree + 1) ** 2
        sh = np.concatenate([sh[:, :want], np.zeros((n, max(want - k, 0), 3), sh.dtype)], 1)
    cols = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2],
            "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    for ch in range(3):
        cols[f"f_dc_{ch}"] = sh[:, 0, ch]
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, -1)  # channel-major, as 3DGS
    for j in range(rest.shape[1]):
        cols[f"f_rest_{j}"] = rest[:, j]
    cols["opacity"] = logit_opacity
    for j in range(3):
        cols[f"scale_{j}"] = log_scales[:, j]
    for j in range(4):
        cols[f"rot_{j}"] = quats[:, j]
    return cols


def ply_columns_to_gaussians(cols: dict, where="PLY") -> dict:
    """Inverse of ``gaussians_to_ply_columns`` (any 3DGS PLY): means, log_scales, quats,
    logit_opacity, sh (N, K, 3)."""
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{j}" for j in range(3)] + \
        [f"rot_{j}" for j in range(4)]
    missing = [k for k in need if k not in cols]
    if missing:
        raise FormatError(where, f"not a 3DGS PLY: missing properties {missing}")
    n = len(cols["x"])
    n_rest = len([k for k in cols if k.startswith("f_rest_")])
    if n_rest % 3 or int(round(np.sqrt(n_rest // 3 + 1))) ** 2 != n_rest // 3 + 1:
        raise FormatError(where, f"{n_rest} f_rest properties do not make an SH degree")
    k = n_rest // 3 + 1
    sh = np.zeros((n, k, 3), np.float32)
    for ch in range(3):
        sh[:, 0, ch] = cols[f"f_dc_{ch}"]
    if k > 1:
        rest = np.stack([cols[f"f_rest_{j}"] for j in range(n_rest)], 1).reshape(n, 3, k - 1)
        sh[:, 1:, :] = np.transpose(rest, (0, 2, 1))
    return {"means": np.stack([cols["x"], cols["y"], cols["z"]], 1),
            "log_scales": np.stack([cols[f"scale_{j}"] for j in range(3)], 1),
            "quats": np.stack([cols[f"rot_{j}"] for j in range(4)], 1),
            "logit_opacity": np.asarray(cols["opacity"]), "sh": sh}


# ---- times ----------------------------------------------------------------------------------------
def export_times(recon, *, frames: slice | None = None, fps: float | None = None) -> list[float]:
    """Seconds to export: the training frames (or a grid at ``fps``), sliced by ``frames``."""
    t0, t1 = float(recon.time_min), float(recon.time_max)
    if fps is not None:
        if not fps > 0:
            raise InputError("--fps", f"must be > 0, got {fps}")
        times = list(t0 + np.arange(int(np.floor((t1 - t0) * fps + 1e-6)) + 1) / fps)
    else:
        times = [float(t) for t in (recon.config or {}).get("frame_times_s") or []]
        if not times:
            f = (recon.config or {}).get("fps") or 30.0
            times = list(t0 + np.arange(int(np.floor((t1 - t0) * f + 1e-6)) + 1) / f)
    if recon.decoder is None:
        times = times[:1]  # a static reconstruction has one state
    sel = times[frames] if frames is not None else times
    if not sel:
        raise InputError("--frames", f"selects none of the {len(times)} frames")
    return sel


def sample_rate(times, fps: float | None = None, *, where="reconstruction") -> float:
    """Samples per second of evenly spaced ``times`` (the k-th time is time code k of a USD
    cache, so this is its timeCodesPerSecond and playback runs in real time); one time: ``fps``,
    else 30. Unevenly spaced times have no one rate: a clear error asking for --fps."""
    t = np.asarray(times, np.float64)
    if len(t) < 2:
        return float(fps or 30.0)
    dt = np.diff(t)
    if not dt.min() > 0 or dt.max() > 1.01 * dt.min():
        raise InputError(where, f"its {len(t)} frame times are not evenly spaced ({dt.min():.4g} to {dt.max():.4g} s "
                                "apart), so they have no one frame rate; give --fps to resample the clip evenly")
    return round(float(1.0 / dt.mean()), 6)


# ---- the exports ----------------------------------------------------------------------------------
def export_ply(anim: ParticleAnimation, t: float, path, *, sh_degree: int | None = 3) -> Path:
    g = anim.at(t, warn=True)
    return write_ply(path, gaussians_to_ply_columns(g["positions"], g["log_scales"], g["quats"],
                                                    g["logit_opacity"], g["sh"], sh_degree=sh_degree))


def write_gaussians_glb(path, means, log_scales, quats, logit_opacity, sh, *, generator: str = "gaussfluids") -> Path:
    """Binary glTF 2.0 of Gaussians with ``KHR_gaussian_splatting`` (the toolkit's quaternions are
    w x y z of any norm, its SH (N, K, 1 or 3) in the 3DGS basis and order, which the extension
    shares). Atomic."""
    from .decoder_np import base_color, sigmoid

    n = len(means)
    sh = np.asarray(sh, np.float32)
    if sh.shape[2] == 1:  # grayscale: the same coefficients in R, G and B
        sh = np.repeat(sh, 3, axis=2)
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0, 0, 0]))
    opacity = sigmoid(np.asarray(logit_opacity, np.float32))
    columns = [("POSITION", "VEC3", np.asarray(means, np.float32)),
               ("COLOR_0", "VEC4", np.concatenate([base_color(sh[:, 0, :]), opacity[:, None]], 1)),
               (f"{GLTF_EXTENSION}:SCALE", "VEC3", np.asarray(log_scales, np.float32)),
               (f"{GLTF_EXTENSION}:ROTATION", "VEC4", q[:, [1, 2, 3, 0]]),
               (f"{GLTF_EXTENSION}:OPACITY", "SCALAR", opacity)]
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    for ell in range(degree + 1):
        for m in range(2 * ell + 1):
            columns.append((f"{GLTF_EXTENSION}:SH_DEGREE_{ell}_COEF_{m}", "VEC3", sh[:, ell * ell + m, :]))
    blob, views, accessors, attributes = bytearray(), [], [], {}
    for k, (name, kind, data) in enumerate(columns):
        arr = np.ascontiguousarray(np.asarray(data, "<f4").reshape(n, -1))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": arr.nbytes})
        acc = {"bufferView": k, "componentType": 5126, "count": n, "type": kind}  # 5126 = FLOAT
        if name == "POSITION":  # required by glTF for positions
            acc["min"], acc["max"] = arr.min(0).tolist(), arr.max(0).tolist()
        accessors.append(acc)
        attributes[name] = k
        blob += arr.tobytes()  # float32 columns keep every view 4-byte aligned
    doc = {"asset": {"version": "2.0", "generator": generator},
           "extensionsUsed": [GLTF_EXTENSION],
           "scene": 0, "scenes": [{"nodes": [0]}],
           # z-up (the toolkit) to y-up (glTF): -90 degrees about x, quaternion x y z w
           "nodes": [{"mesh": 0, "name": "gaussians", "rotation": [-float(np.sqrt(0.5)), 0.0, 0.0, float(np.sqrt(0.5))]}],
           "meshes": [{"name": "gaussians", "primitives": [{
               "mode": 0, "attributes": attributes,
               "extensions": {GLTF_EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                               "projection": "perspective", "sortingMethod": "cameraDistance"}}}]}],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    import json
    import struct

    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned: JSON padded with spaces, BIN with zeros
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return Path(path)


def export_gltf(anim: ParticleAnimation, t: float, path) -> Path:
    g = anim.at(t, warn=True)
    return write_gaussians_glb(path, g["positions"], g["log_scales"], g["quats"], g["logit_opacity"], g["sh"],
                               generator=f"gaussfluids (t = {float(t):.6g} s)")


def particle_radii(log_scales, radius_scale: float = 1.0):
    """A point radius per particle: ``radius_scale`` x the geometric mean of its Gaussian scales."""
    return radius_scale * np.exp(np.asarray(log_scales, np.float64).mean(1))


def export_particles(anim: ParticleAnimation, times, out_dir, radius_scale: float = 1.0) -> list[Path]:
    out = []
    for k, t in enumerate(times):
        g = anim.at(t, velocity=True, warn=True)
        p, v = g["positions"], g["velocities"]
        out.append(write_ply(Path(out_dir) / f"particles_{k:05d}.ply", {
            "x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
            "radius": particle_radii(g["log_scales"], radius_scale), "opacity": g["opacities"]}))
    return out


def write_vtk_points(path, positions, vectors: dict, scalars: dict, *, title: str = "gaussfluids particles") -> Path:
    """A legacy VTK file (version 4.2, binary: big-endian float32 / int32) of points as vertex
    cells of an unstructured grid (the dataset kind every legacy reader takes, meshio included), with point data: ``vectors`` (name -> (N, 3)) and ``scalars`` (name -> (N,)). Atomic."""
    p = np.asarray(positions, np.float64)
    n = len(p)
    out = [f"# vtk DataFile Version 4.2\n{title[:250]}\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS {n} float\n".encode(),
           p.astype(">f4").tobytes(), f"\nCELLS {n} {2 * n}\n".encode(),
           np.stack([np.ones(n, ">i4"), np.arange(n, dtype=">i4")], 1).astype(">i4").tobytes(),
           f"\nCELL_TYPES {n}\n".encode(), np.ones(n, ">i4").tobytes(),  # 1 = VTK_VERTEX
           f"\nPOINT_DATA {n}\n".encode()]
    for name, v in vectors.items():
        out += [f"VECTORS {name} float\n".encode(), np.asarray(v, np.float64).reshape(n, 3).astype(">f4").tobytes(), b"\n"]
    for name, v in scalars.items():
        out += [f"SCALARS {name} float 1\nLOOKUP_TABLE default\n".encode(),
                np.asarray(v, np.float64).reshape(n).astype(">f4").tobytes(), b"\n"]
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(b"".join(out))
    return Path(path)


def export_vtk(anim: ParticleAnimation, times, out_dir, radius_scale: float = 1.0) -> list[Path]:
    out = []
    for k, t in enumerate(times):
        g = anim.at(t, velocity=True, warn=True)
        out.append(write_vtk_points(Path(out_dir) / f"particles_{k:05d}.vtk", g["positions"],
                                    {"velocity": g["velocities"]},
                                    {"radius": particle_radii(g["log_scales"], radius_scale), "opacity": g["opacities"]},
                                    title=f"gaussfluids particles t={float(t):.6g} s"))
    return out


def export_vdb(anim: ParticleAnimation, times, out_dir, *, voxel: float | None = None,
               radius_scale: float = 1.0) -> list[Path]:
    from .caches import density_grid, write_vdb_density

    out = []
    for k, t in enumerate(times):
        g = anim.at(t, warn=True)
        sig = particle_radii(g["log_scales"], radius_scale)
        vx = voxel or 0.5 * float(np.median(sig))
        dense, lo = density_grid(g["positions"], sig, g["opacities"], vx)
        out.append(Path(write_vdb_density(Path(out_dir) / f"density_{k:05d}.vdb", dense, lo, vx)))
    return out


def export_usd(anim: ParticleAnimation, times, path, *, fps: float, radius_scale: float = 1.0) -> Path:
    """Time code k = the k-th exported time; ``fps`` time codes per second."""
    from .caches import write_usd_points

    def samples():
        for k, t in enumerate(times):
            g = anim.at(t, velocity=True, warn=True)
            yield k, g["positions"], particle_radii(g["log_scales"], radius_scale), g["velocities"], \
                g["colors"], g["opacities"]

    return Path(write_usd_points(path, samples(), fps=fps, start=0, end=len(times) - 1,
                                 metadata={"times_s": [float(t) for t in times]}))


__all__ = ["FORMATS", "SH_DEGREES", "write_ply", "read_ply", "gaussians_to_ply_columns", "ply_columns_to_gaussians",
           "export_times", "sample_rate", "export_ply", "export_gltf", "write_gaussians_glb", "export_particles", "export_vtk", "write_vtk_points", "export_vdb", "export_usd", "particle_radii"]
