"""The PINF / HyFluid video layout (``info.json`` + one video per camera) and footage loaded at a
smaller size (``--resolution`` / ``--downscale``)."""

import json
import math

import numpy as np
import pytest

from gf_core.camera import Camera
from gf_core.data import has_split, load_dataset, write_video
from gf_core.data.pinf import Y_UP_TO_Z_UP
from gf_core.errors import InputError

# the ScalarReal capture's box, as HyFluid ships it
VOXEL_MATRIX = [[7.549790126404332e-08, 0.0, 1.0, 0.081816665828228], [0.0, 1.0, 0.0, -0.044627271592617035],
                [-1.0, 0.0, 7.549790126404332e-08, -0.004908999893814325], [0.0, 0.0, 0.0, 1.0]]
VOXEL_SCALE = [0.4909, 0.73635, 0.4909]


def look_at_gl(eye, target, up=(0.0, 1.0, 0.0)):
    """An OpenGL camera-to-world (x right, y up, looking down -z) at ``eye`` towards ``target``."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, np.cross(back, right), back, eye
    return m


def nerf_pixel(c2w_gl, angle_x, w, h, p):
    """Where a world point lands in a NeRF camera (the convention written out by hand)."""
    q = np.linalg.inv(c2w_gl) @ np.append(p, 1.0)
    f = 0.5 * w / math.tan(0.5 * angle_x)
    return np.array([w / 2 + f * q[0] / -q[2], h / 2 - f * q[1] / -q[2]])


def write_pinf(root, views, *, w=12, h=20, frames=4, rate=30.0, test=1, rng=None, **top):
    """A y-up capture: ``views`` training + ``test`` held-out portrait videos around the origin."""
    rng = rng or np.random.default_rng(0)
    root.mkdir(parents=True, exist_ok=True)
    entries, poses, imgs = [], [], []
    for v in range(views + test):
        a = 2 * math.pi * v / (views + test)
        c2w = look_at_gl([2 * math.sin(a), 0.5, 2 * math.cos(a)], [0.0, 0.3, 0.0])
        frames_v = rng.integers(0, 256, size=(frames, h, w, 3), dtype=np.uint8)
        write_video(root / f"cam{v:02d}.mkv", frames_v, rate)
        entries.append({"file_name": f"cam{v:02d}.mkv", "frame_rate": rate, "frame_num": frames,
                        "camera_angle_x": 0.6, "camera_hw": [h, w], "transform_matrix": c2w.tolist()})
        poses.append(c2w)
        imgs.append(frames_v)
    info = {"train_videos": entries[:views], "test_videos": entries[views:], "frame_bkg_color": [0.0, 0.0, 0.0],
            "voxel_matrix": VOXEL_MATRIX, "voxel_scale": VOXEL_SCALE, "render_center": [0.33, 0.38, -0.26],
            "near": 1.1, "far": 1.5, "phi": 20.0, "rot": "Y", **top}
    (root / "info.json").write_text(json.dumps(info))
    return poses, imgs


def test_pinf_layout_conventions(tmp_path):
    """Detected by itself; portrait camera_hw is [H, W]; transform_matrix is OpenGL camera-to-world;
    a y-up world becomes the toolkit's z-up one (the file's up is +z after load); t = k / frame_rate;
    test_videos are the held-out cameras with their own view ids; the voxel box is the scene box."""
    poses, imgs = write_pinf(tmp_path, 3, rate=25.0)
    train, test = load_dataset(tmp_path), load_dataset(tmp_path, split="test")
    assert train.meta["layout"] == "pinf" and has_split(tmp_path, "test")
    assert train.views == [0, 1, 2] and test.views == [3]
    assert np.allclose(train.times, np.arange(4) / 25.0)
    p_file = np.array([0.1, 0.45, -0.2])                       # a point in the file's (y-up) world
    p_world = (Y_UP_TO_Z_UP @ np.append(p_file, 1.0))[:3]
    assert np.allclose(p_world, [0.1, 0.2, 0.45])              # file +y is the toolkit's +z
    for ds, first in ((train, 0), (test, 3)):
        for v, cam in ds.cameras().items():
            assert (cam.width, cam.height) == (12, 20)         # portrait: 12 wide, 20 tall
            uv, z = cam.project(p_world)
            assert z > 0 and np.allclose(uv, nerf_pixel(poses[v], 0.6, 12, 20, p_file), atol=1e-9)
            up_in_image = cam.world_to_camera[:3, :3] @ [0, 0, 1.0]
            assert up_in_image[1] < -0.9                       # world up is image up (OpenCV y points down)
    s = test[test.indices(time=2 / 25.0)[0]]
    assert np.allclose(s.image.numpy(), imgs[3][2] / 255.0)   # the held-out video's third frame
    lo, hi = np.array(train.meta["scene_box"])
    # HyFluid's box in the file: x [0.0818, 0.5727], y [-0.0446, 0.6917], z [-0.4958, -0.0049]
    assert np.allclose(lo, [0.081817, 0.004909, -0.044627], atol=1e-6)
    assert np.allclose(hi, [0.081817 + 0.4909, 0.004909 + 0.4909, -0.044627 + 0.73635], atol=1e-6)


def test_pinf_z_up_file_is_used_as_it_is(tmp_path):
    write_pinf(tmp_path, 2, rot="Z")
    ds = load_dataset(tmp_path)
    assert np.allclose(ds.meta["world_from_file"], np.eye(4))


@pytest.mark.parametrize("change, says", [
    (lambda i: i["train_videos"][0].pop("file_name"), "train_videos[0]: missing 'file_name'"),
    (lambda i: i["train_videos"][1].update(camera_hw=[12, 20]), "says camera_hw [12, 20] (height, width)"),
    (lambda i: i["train_videos"][0].update(frame_rate=0), "'frame_rate' must be a positive number"),
    (lambda i: i["train_videos"][0].update(frame_num=9), "has 4 frames but info.json says 'frame_num' 9"),
    (lambda i: i["train_videos"][0].update(camera_angle_x=4.0), "'camera_angle_x' must be the horizontal field"),
    (lambda i: i["train_videos"][0].pop("transform_matrix"), "missing 'transform_matrix'"),
    (lambda i: i["train_videos"][0].update(transform_matrix=[[1, 0], [0, 1]]), "'transform_matrix' must be a 4x4"),
    (lambda i: i["train_videos"][1].update(frame_rate=24), "different 'frame_rate' values"),
    (lambda i: i.update(rot="X"), "'rot' (the world's up axis) must be"),
    (lambda i: i.update(voxel_scale=[1, -1, 1]), "'voxel_scale' must be one or three positive numbers"),
    (lambda i: i.pop("voxel_scale"), "'voxel_matrix' and 'voxel_scale' come together"),
    (lambda i: i.update(frame_bkg_color="black"), "'frame_bkg_color' must be 3 numbers"),
    (lambda i: i.update(train_videos=[]), "has no 'train_videos' list"),
    (lambda i: i["train_videos"][0].update(file_name="gone.mp4"), "video file does not exist"),
])
def test_pinf_bad_entries_give_one_line_each(tmp_path, change, says):
    write_pinf(tmp_path, 2)
    info = json.loads((tmp_path / "info.json").read_text())
    change(info)
    (tmp_path / "info.json").write_text(json.dumps(info))
    with pytest.raises(InputError) as e:
        load_dataset(tmp_path)
    msg = str(e.value)
    assert says in msg and "\n" not in msg
    assert "info.json" in msg or ".mkv" in msg or ".mp4" in msg


def blob_video_dataset(root, cam: Camera, point, frames=3):
    """A one-camera video dataset whose frames show a small bright disc centred on ``point``'s
    projection (drawn at sub-pixel precision, 4x4 supersampled)."""
    (u, v), _ = cam.project(np.asarray(point, np.float64))
    ys, xs = np.mgrid[0:cam.height * 4, 0:cam.width * 4]
    inside = (xs + 0.5) / 4 - u, (ys + 0.5) / 4 - v
    disc = ((inside[0] ** 2 + inside[1] ** 2) < 3.0 ** 2).reshape(cam.height, 4, cam.width, 4).mean((1, 3))
    img = np.repeat(np.rint(disc * 255).astype(np.uint8)[..., None], 3, -1)
    write_video(root / "cam0.mkv", [img] * frames, 30.0)
    (root / "cameras.json").write_text(json.dumps({"fps": 30.0, "cameras": [{
        "video": "cam0.mkv", "transform_matrix": cam.to_blender_c2w().tolist(), "fl_x": cam.fx, "fl_y": cam.fy,
        "cx": cam.cx, "cy": cam.cy}]}))


def centroid(img):
    w = img[..., 0].astype(np.float64)
    ys, xs = np.mgrid[0:w.shape[0], 0:w.shape[1]]
    return np.array([((xs + 0.5) * w).sum() / w.sum(), ((ys + 0.5) * w).sum() / w.sum()])


@pytest.mark.parametrize("kw", [dict(resolution=30), dict(downscale=4)])
def test_smaller_footage_keeps_the_projection_of_a_point(tmp_path, kw):
    """Area-averaged pixels and scaled intrinsics: a world point's projection in the smaller camera
    is where its image lands in the smaller image (to a small fraction of a pixel)."""
    c2w = look_at_gl([0.3, -2.0, 0.6], [0.0, 0.0, 0.2], up=(0, 0, 1))
    cam = Camera.from_blender(c2w, 120, 88, fx=100.0, cx=61.3, cy=42.7)
    point = [0.12, 0.05, 0.31]
    blob_video_dataset(tmp_path, cam, point)
    full, small = load_dataset(tmp_path), load_dataset(tmp_path, **kw)
    c = small.frames[0].camera
    assert (c.width, c.height) == (30, 22)
    assert small.meta["dataset_options"] == kw
    uv_full, _ = cam.project(np.array(point))
    uv, _ = c.project(np.array(point))
    assert np.allclose(centroid(full.load(0)[0]), uv_full, atol=0.05)
    assert np.allclose(centroid(small.load(0)[0]), uv, atol=0.05)
    assert small.load(0)[0].shape == (22, 30, 3)
    # each frame decoded once; the cache holds the small images
    for _ in range(2):
        for i in range(len(small)):
            small.load(i)
    assert small.frames_decoded == len(small) and small._cached == len(small) * 22 * 30 * 3


def test_smaller_footage_refuses_upscaling_and_bad_factors(tmp_path):
    cam = Camera.from_blender(look_at_gl([0, -2, 0.5], [0, 0, 0.2], up=(0, 0, 1)), 40, 30, fx=40.0)
    blob_video_dataset(tmp_path, cam, [0, 0, 0.2], frames=1)
    with pytest.raises(InputError, match="would upscale"):
        load_dataset(tmp_path, resolution=80)
    for k in (0.5, 0, float("nan")):
        with pytest.raises(InputError, match="--downscale"):
            load_dataset(tmp_path, downscale=k)
    with pytest.raises(InputError, match="not both"):
        load_dataset(tmp_path, resolution=20, downscale=2)


def test_reconstruct_and_evaluate_read_the_footage_at_the_same_size(tmp_path, monkeypatch):
    """``gf-cli reconstruct --resolution`` on a PINF capture; ``gf-cli evaluate`` reads the held-out
    camera the way the run read its images (recon.h5's dataset_options)."""
    from gf_cli.main import main
    from gf_core.formats.hdf5 import read_recon

    write_pinf(tmp_path / "ds", 3, w=24, h=40, frames=3)
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("[model]\ninit_particles = 64\nmax_particles = 128\n[decoder]\nhidden_width = 16\n"
                   "hidden_layers = 1\nfeature_dim = 4\n[train]\neval_every = 20\ncheckpoint_every = 20\n")
    run = tmp_path / "run"
    assert main(["reconstruct", str(tmp_path / "ds"), "--out", str(run), "--preset", "smoke", "--config", str(cfg),
                 "--grayscale", "--background-removal", "xor", "--resolution", "12", "--iterations", "20",
                 "--quiet"]) == 0
    r = read_recon(run / "recon.h5")
    assert r.config["dataset_options"] == {"grayscale": True, "background_removal": "xor", "resolution": 12}
    assert r.channels == 1
    import gf_core.data

    seen, load = [], gf_core.data.load_dataset
    monkeypatch.setattr(gf_core.data, "load_dataset", lambda *a, **k: seen.append(load(*a, **k)) or seen[-1])
    assert main(["evaluate", str(run)]) == 0
    assert [(d.channels, d.background_removal, d.frames[0].camera.width) for d in seen] == [(1, "xor", 12)] * 2
    ev = json.loads((run / "eval.json").read_text())
    assert math.isfinite(ev["test"]["psnr_mean"]) and math.isfinite(ev["train"]["psnr_mean"])


def test_pinf_box_reads_voxel_matrix_as_hyfluid_does(tmp_path):
    """HyFluid swaps voxel_matrix's first and third columns before scaling by voxel_scale: with
    unequal x and z scales the box tells the two readings apart."""
    write_pinf(tmp_path, 2, voxel_scale=[0.2, 0.7, 0.5])
    lo, hi = np.array(load_dataset(tmp_path).meta["scene_box"])
    tx, ty, tz = 0.081816665828228, -0.044627271592617035, -0.004908999893814325
    # in the file: x [tx, tx + 0.2], y [ty, ty + 0.7], z [tz - 0.5, tz]; then y-up -> z-up: (x, -z, y)
    assert np.allclose(lo, [tx, -tz, ty]) and np.allclose(hi, [tx + 0.2, -tz + 0.5, ty + 0.7])
