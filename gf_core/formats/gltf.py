"""Gaussians as binary glTF 2.0 (``.glb``) with the Khronos ``KHR_gaussian_splatting`` extension:
a POINTS primitive with POSITION, ``:SCALE`` (log), ``:ROTATION`` (unit quaternion x y z w),
``:OPACITY`` (in [0, 1]), ``:SH_DEGREE_l_COEF_n`` (RGB, every coefficient of the model's degree),
COLOR_0 (base colour and opacity, for viewers that draw plain points); kernel ellipse, colour space
srgb_rec709_display. The node turns the toolkit's z-up world into glTF's y-up. Numpy only."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from .decoder_np import base_color, sigmoid, unit_quaternions
from .hdf5 import atomic_path

GLTF_EXTENSION = "KHR_gaussian_splatting"


def write_gaussians_glb(path, means, log_scales, quats, logit_opacity, sh, *, generator: str = "gaussfluids") -> Path:
    """Binary glTF 2.0 of Gaussians with ``KHR_gaussian_splatting`` (the toolkit's quaternions are
    w x y z of any norm, its SH (N, K, 1 or 3) in the 3DGS basis and order, which the extension
    shares). Atomic."""
    n = len(means)
    sh = np.asarray(sh, np.float32)
    if sh.shape[2] == 1:  # grayscale: the same coefficients in R, G and B
        sh = np.repeat(sh, 3, axis=2)
    q = unit_quaternions(quats)
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
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned: JSON padded with spaces, BIN with zeros
    blob += b"\0" * (-len(blob) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    return Path(path)


__all__ = ["GLTF_EXTENSION", "write_gaussians_glb"]
