"""Pinhole cameras.

Convention inside ``gf_core`` (OpenCV): camera x right, y down, z forward; a camera stores the
world-to-camera rigid transform (4x4) and intrinsics fx, fy, cx, cy in pixels.

Pixel coordinates are continuous with the image spanning [0, W] x [0, H]: pixel (row i, column j)
has its centre at (u, v) = (j + 0.5, i + 0.5). This is the NeRF / instant-ngp convention, so a
centred principal point is cx = W / 2. (An OpenCV calibration, whose pixel centres sit on integers,
needs +0.5 on cx and cy: ``Camera.from_opencv_calibration`` does that.)

Blender and NeRF files store camera-to-world in the OpenGL convention (x right, y up, -z forward);
``from_blender`` / ``to_blender_c2w`` convert, once, at the loader.

Cameras are plain numpy (float64) so that file loaders need no torch; ``to_torch`` hands the
renderer what it needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, short_repr

# OpenGL camera axes -> OpenCV camera axes (flip y and z); its own inverse.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _as_matrix(m, shape, what: str, where: str) -> np.ndarray:
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"{what} must be a {'x'.join(map(str, shape))} matrix of numbers, "
                                f"got {short_repr(m)}") from None
    if a.shape != shape:
        raise InputError(where, f"{what} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(where, f"{what} contains NaN or infinite values")
    return a


def _check_rigid(T: np.ndarray, what: str, where: str) -> None:
    R = T[:3, :3]
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise InputError(where, f"{what}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InputError(where, f"{what}: rotation part is not a proper rotation (orthonormal, det +1)")


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics in pixels, OpenCV world-to-camera pose, image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    near: float = 0.01
    name: str = ""

    def __post_init__(self):
        where = self.name or "camera"
        for k in ("fx", "fy", "cx", "cy", "near"):
            v = float(getattr(self, k))
            if not math.isfinite(v):
                raise InputError(where, f"{k} is not finite ({v})")
            object.__setattr__(self, k, v)
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(where, f"focal length must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(where, f"image size must be positive, got {self.width}x{self.height}")
        if self.near <= 0:
            raise InputError(where, f"near plane must be positive, got {self.near}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        T = _as_matrix(self.world_to_camera, (4, 4), "world_to_camera", where)
        _check_rigid(T, "world_to_camera", where)
        T = T.copy()
        T.setflags(write=False)
        object.__setattr__(self, "world_to_camera", T)

    # ---- constructors -------------------------------------------------------------------------
    @staticmethod
    def focal_from_angle(angle: float, size: int) -> float:
        """Focal length in pixels from a full field-of-view angle (radians) across ``size`` pixels."""
        if not (0.0 < angle < math.pi):
            raise ValueError(f"field of view must be in (0, pi) radians, got {angle}")
        return 0.5 * size / math.tan(0.5 * angle)

    @classmethod
    def from_blender(cls, c2w_gl, width: int, height: int, *, fx: float | None = None,
                     fy: float | None = None, cx: float | None = None, cy: float | None = None,
                     camera_angle_x: float | None = None, camera_angle_y: float | None = None,
                     name: str = "", near: float = 0.01) -> "Camera":
        """From a Blender/NeRF camera-to-world matrix (OpenGL axes) and NeRF-style intrinsics.

        Focal length comes from ``fx``/``fy`` or from ``camera_angle_x`` (horizontal FOV, radians,
        as in NeRF's transforms.json); square pixels are assumed when only one is given.
        """
        where = name or "camera"
        c2w = _as_matrix(c2w_gl, (4, 4), "camera-to-world matrix", where)
        if fx is None and camera_angle_x is not None:
            fx = cls.focal_from_angle(camera_angle_x, width)
        if fy is None and camera_angle_y is not None:
            fy = cls.focal_from_angle(camera_angle_y, height)
        if fx is None and fy is None:
            raise InputError(where, "no focal length: give fl_x/fl_y or camera_angle_x")
        fx = fy if fx is None else fx
        fy = fx if fy is None else fy
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
        _check_rigid(c2w, "camera-to-world matrix", where)
        w2c = np.linalg.inv(c2w @ GL_TO_CV)
        return cls(fx, fy, cx, cy, width, height, w2c, near=near, name=name)

    @classmethod
    def from_opencv_calibration(cls, K, world_to_camera, width: int, height: int,
                                name: str = "", near: float = 0.01) -> "Camera":
        """From an OpenCV calibration (pixel centres on integers): shifts cx, cy by +0.5."""
        K = _as_matrix(K, (3, 3), "K", name or "camera")
        return cls(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, width, height,
                   world_to_camera, near=near, name=name)

    @classmethod
    def look_at(cls, eye, target, up, *, fx: float, width: int, height: int,
                fy: float | None = None, name: str = "") -> "Camera":
        """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image."""
        eye = np.asarray(eye, np.float64)
        fwd = np.asarray(target, np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, np.float64))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError("look_at: up is parallel to the viewing direction")
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
        w2c = np.eye(4)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        return cls(fx, fx if fy is None else fy, width / 2.0, height / 2.0, width, height, w2c,
                   name=name)

    # ---- derived quantities --------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def camera_to_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """Camera position in world coordinates."""
        R, t = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        return -R.T @ t

    @property
    def camera_angle_x(self) -> float:
        return 2.0 * math.atan(0.5 * self.width / self.fx)

    def to_blender_c2w(self) -> np.ndarray:
        """Camera-to-world in the OpenGL/Blender convention (the inverse of ``from_blender``)."""
        return self.camera_to_world @ GL_TO_CV

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) -> pixel coordinates (..., 2) and camera depth z (...).

        Points at or behind the camera get NaN pixel coordinates (their depth says why).
        """
        p = np.asarray(points, np.float64)
        pc = p @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(z > 0, z, np.nan)
            uv = np.stack([self.fx * pc[..., 0] / zs + self.cx, self.fy * pc[..., 1] / zs + self.cy], -1)
        return uv, z

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for half resolution)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h,
                      self.world_to_camera, near=self.near, name=self.name)

    def to_torch(self, device=None, dtype=None):
        """(viewmat 4x4, intrinsics tensor [fx, fy, cx, cy]) as torch tensors."""
        import torch

        dtype = dtype or torch.float32
        viewmat = torch.tensor(self.world_to_camera, dtype=dtype, device=device)
        intr = torch.tensor([self.fx, self.fy, self.cx, self.cy], dtype=dtype, device=device)
        return viewmat, intr

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width,
                "height": self.height, "world_to_camera": self.world_to_camera.tolist(),
                "near": self.near, "name": self.name}

    @classmethod
    def from_dict(cls, d: dict, where: str = "camera") -> "Camera":
        try:
            return cls(d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"],
                       d["world_to_camera"], near=d.get("near", 0.01), name=d.get("name", ""))
        except KeyError as e:
            raise InputError(where, f"camera is missing the key {e.args[0]!r}") from None

    def __eq__(self, other):
        if not isinstance(other, Camera):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self):
        return hash((self.fx, self.fy, self.cx, self.cy, self.width, self.height,
                     self.world_to_camera.tobytes()))

    def allclose(self, other: "Camera", rtol=1e-9, atol=1e-9) -> bool:
        return (self.width == other.width and self.height == other.height
                and np.allclose([self.fx, self.fy, self.cx, self.cy],
                                [other.fx, other.fy, other.cx, other.cy], rtol=rtol, atol=atol)
                and np.allclose(self.world_to_camera, other.world_to_camera, rtol=rtol, atol=atol))


def frontal_arc(n: int, *, radius: float, target=(0.0, 0.0, 0.0), height: float = 0.0,
                arc_degrees: float = 90.0, fx: float, width: int, height_px: int,
                up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """``n`` cameras on a horizontal arc in front of ``target`` (the NeuroFluid-like frontal rig).

    The arc is centred on the -y side of the target (Blender's front view), z up.
    """
    target = np.asarray(target, np.float64)
    angles = np.linspace(-0.5, 0.5, n) * math.radians(arc_degrees) if n > 1 else np.zeros(1)
    cams = []
    for k, a in enumerate(angles):
        eye = target + np.array([radius * math.sin(a), -radius * math.cos(a), height])
        cams.append(Camera.look_at(eye, target, up, fx=fx, width=width, height=height_px,
                                   name=f"view_{k}"))
    return cams
