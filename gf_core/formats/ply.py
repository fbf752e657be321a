"""PLY files (binary little-endian): a vertex element of float32 properties (``write_ply`` /
``read_ply``), and the 3DGS layout of Gaussians in it (x y z nx ny nz f_dc_0..2 f_rest_* opacity
scale_0..2 rot_0..3, with the activations 3DGS expects: logit opacity, log scales, quaternion
w x y z, SH coefficients with f_rest channel-major). Numpy only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from .hdf5 import atomic_path


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


__all__ = ["write_ply", "read_ply", "SH_DEGREES", "gaussians_to_ply_columns", "ply_columns_to_gaussians"]
