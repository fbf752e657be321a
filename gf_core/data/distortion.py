"""Lens distortion of calibrated cameras, removed when images are loaded.

Real rigs are calibrated with a distortion model (nerfstudio's ``transforms.json`` and COLMAP
write OpenCV's): the renderer is a pinhole camera, so every image (and mask) is resampled once,
when first decoded, to the pinhole image of the same size and intrinsics. Models, on normalised
camera coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), r^2 = x^2 + y^2:

- ``OPENCV`` (k1, k2, p1, p2, and k3 when given; OpenCV's radial-tangential model):
  x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2), y_d likewise with
  p1 (r^2 + 2 y^2) + 2 p2 x y.
- ``OPENCV_FISHEYE`` (k1..k4; OpenCV's fisheye model): theta = atan(r),
  theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), (x_d, y_d) = theta_d / r (x, y).

Each undistorted pixel centre is mapped through the model into the recorded image and sampled
bilinearly there (``cv2.remap``); pixels whose source lies outside the recorded image repeat its
border.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

MODELS = {"OPENCV": ("k1", "k2", "p1", "p2", "k3"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}
PINHOLES = ("PINHOLE", "SIMPLE_PINHOLE")


@dataclass(frozen=True)
class Distortion:
    model: str          # a key of MODELS
    coeffs: tuple       # in the order of MODELS[model]

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised pinhole coordinates -> where the lens puts them (the model's forward map)."""
        c = dict(zip(MODELS[self.model], self.coeffs))
        r2 = x * x + y * y
        if self.model == "OPENCV":
            radial = 1 + r2 * (c["k1"] + r2 * (c["k2"] + r2 * c["k3"]))
            xd = x * radial + 2 * c["p1"] * x * y + c["p2"] * (r2 + 2 * x * x)
            yd = y * radial + c["p1"] * (r2 + 2 * y * y) + 2 * c["p2"] * x * y
            return xd, yd
        r = np.sqrt(r2)
        th = np.arctan(r)
        th2 = th * th
        thd = th * (1 + th2 * (c["k1"] + th2 * (c["k2"] + th2 * (c["k3"] + th2 * c["k4"]))))
        scale = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
        return x * scale, y * scale


def from_keys(d: dict, where_file, where: str) -> Distortion | None:
    """The distortion a transforms frame (top level merged with the frame) describes: nerfstudio's
    ``camera_model`` and ``k1 k2 k3 k4 p1 p2``; None for a pinhole or all-zero coefficients."""
    keys = ("k1", "k2", "k3", "k4", "p1", "p2")
    model = d.get("camera_model")
    present = {k: d[k] for k in keys if d.get(k) is not None}
    if model is None:
        if not present:
            return None
        model = "OPENCV_FISHEYE" if "k4" in present and not ({"p1", "p2"} & set(present)) else "OPENCV"
    if not isinstance(model, str) or model.upper() not in (*MODELS, *PINHOLES):
        raise InputError(where_file, f"{where}: camera_model {model!r} is not supported (supported: "
                                     f"{', '.join((*MODELS, *PINHOLES))})")
    model = model.upper()
    if model in PINHOLES:
        if any(float(v) != 0 for v in present.values()):
            raise InputError(where_file, f"{where}: camera_model {model} has no distortion, but "
                                         f"{', '.join(sorted(present))} are given")
        return None
    extra = sorted(set(present) - set(MODELS[model]))
    if extra:
        raise InputError(where_file, f"{where}: {', '.join(extra)} are not coefficients of camera_model {model} "
                                     f"(it takes {', '.join(MODELS[model])})")
    coeffs = []
    for k in MODELS[model]:
        v = present.get(k, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(where_file, f"{where}: distortion coefficient {k} must be a finite number, got {v!r}")
        coeffs.append(float(v))
    return None if not any(coeffs) else Distortion(model, tuple(coeffs))


def undistort_maps(camera, dist: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 (H, W) for ``cv2.remap``: for each pixel of the pinhole image, the
    position (cv2 convention: pixel centres on integers) in the recorded image to sample."""
    u = np.arange(camera.width, dtype=np.float64) + 0.5
    v = np.arange(camera.height, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid(u, v)
    xd, yd = dist.distort((uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy)
    return ((xd * camera.fx + camera.cx - 0.5).astype(np.float32),
            (yd * camera.fy + camera.cy - 0.5).astype(np.float32))


def undistort(img: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The pinhole image of a recorded one (H, W, C), its dtype kept (rounded for integers)."""
    import cv2

    src = img.astype(np.float32)
    out = cv2.remap(src, maps[0], maps[1], interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if out.ndim == 2:
        out = out[..., None]
    if img.dtype.kind == "u":
        return np.clip(np.rint(out), 0, np.iinfo(img.dtype).max).astype(img.dtype)
    return out.astype(img.dtype)


__all__ = ["Distortion", "MODELS", "PINHOLES", "from_keys", "undistort_maps", "undistort"]
