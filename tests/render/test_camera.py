import math

import numpy as np
import pytest

from gf_core.camera import GL_TO_CV, Camera, frontal_arc
from gf_core.errors import InputError


def random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_blender_round_trip(rng):
    for _ in range(20):
        c2w = np.eye(4)
        c2w[:3, :3] = random_rotation(rng)
        c2w[:3, 3] = rng.normal(size=3) * 3
        cam = Camera.from_blender(c2w, 400, 300, camera_angle_x=0.69)
        assert np.allclose(cam.to_blender_c2w(), c2w, atol=1e-12)
        assert np.allclose(cam.center, c2w[:3, 3], atol=1e-12)
        assert math.isclose(cam.camera_angle_x, 0.69, rel_tol=1e-12)
        again = Camera.from_dict(cam.to_dict())
        assert again == cam


def test_camera_angle_x_focal():
    cam = Camera.from_blender(np.eye(4), 400, 400, camera_angle_x=2 * math.atan(0.5))
    assert math.isclose(cam.fx, 400.0) and math.isclose(cam.fy, 400.0)
    assert (cam.cx, cam.cy) == (200.0, 200.0)


def test_blender_camera_looks_down_minus_z():
    # Blender camera at z=5 with identity rotation looks down -z (OpenGL): a point at the
    # origin is in front of it, at depth 5, on the optical axis.
    c2w = np.eye(4)
    c2w[2, 3] = 5.0
    cam = Camera.from_blender(c2w, 100, 80, fx=50.0)
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert np.allclose(z, 5.0)
    assert np.allclose(uv[0], [50.0, 40.0])
    assert np.allclose(uv[1], [50.0 + 50.0 / 5.0, 40.0])     # world +x -> image right
    assert np.allclose(uv[2], [50.0, 40.0 - 50.0 / 5.0])     # world +y (Blender up) -> image up


def test_projection_known_pixels():
    cam = Camera(fx=100.0, fy=120.0, cx=64.0, cy=48.0, width=128, height=96)
    pts = np.array([[0.0, 0.0, 2.0], [1.0, 0.5, 2.0], [-0.64, -0.4, 1.0], [0.0, 0.0, -1.0]])
    uv, z = cam.project(pts)
    assert np.allclose(uv[0], [64.0, 48.0])
    assert np.allclose(uv[1], [64.0 + 50.0, 48.0 + 30.0])
    assert np.allclose(uv[2], [0.0, 0.0])   # the image corner (continuous coords)
    assert np.isnan(uv[3]).all() and z[3] < 0


def test_look_at_and_arc():
    cams = frontal_arc(5, radius=3.0, target=(0, 0, 0.5), fx=300, width=64, height_px=64)
    assert len(cams) == 5
    for cam in cams:
        uv, z = cam.project(np.array([0.0, 0.0, 0.5]))
        assert np.allclose(uv, [32.0, 32.0]) and np.isclose(z, 3.0)
        # z-up world: a point above the target projects above the centre (smaller v)
        uv2, _ = cam.project(np.array([0.0, 0.0, 1.0]))
        assert uv2[1] < 32.0


def test_opencv_calibration_shift_and_scaled():
    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    cam = Camera.from_opencv_calibration(K, np.eye(4), 64, 48)
    assert (cam.cx, cam.cy) == (32.0, 24.0)
    half = cam.scaled(0.5)
    assert (half.width, half.height, half.fx, half.cx) == (32, 24, 50.0, 16.0)


@pytest.mark.parametrize("kwargs, msg", [
    (dict(fx=0.0), "focal length"),
    (dict(fx=float("nan")), "not finite"),
    (dict(width=0), "image size"),
])
def test_bad_cameras(kwargs, msg):
    base = dict(fx=10.0, fy=10.0, cx=5.0, cy=5.0, width=10, height=10)
    base.update(kwargs)
    with pytest.raises(InputError, match=msg):
        Camera(**base)


def test_non_rigid_pose_rejected():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(InputError, match="rotation"):
        Camera(10, 10, 5, 5, 10, 10, T)
    assert np.allclose(GL_TO_CV @ GL_TO_CV, np.eye(4))
