"""Tiny datasets written to disk in every supported layout, loaded back exactly."""

import json
import time

import numpy as np
import pytest
import torch

from gf_core.camera import Camera, frontal_arc
from gf_core.data import load_dataset, load_grayscale, write_video
from gf_core.data.images import write_png
from gf_core.data.writers import frame_entry, write_nerf_dataset
from gf_core.errors import InputError
from gf_core.formats.hdf5 import SimData, write_sim

W, H, VIEWS, FRAMES, FPS = 24, 16, 3, 4, 30.0


def rig():
    return frontal_arc(VIEWS, radius=2.0, fx=20.0, width=W, height_px=H)


def images(rng, channels=4):
    return rng.integers(0, 256, size=(VIEWS, FRAMES, H, W, channels), dtype=np.uint8)


def check(ds, cams, imgs, times, alpha=True):
    assert len(ds) == VIEWS * FRAMES and ds.views == list(range(VIEWS))
    assert np.allclose(ds.times, times)
    for s in ds:
        v = s.view_id
        f = int(np.argmin(np.abs(times - s.time)))
        assert s.camera.allclose(cams[v], atol=1e-9), (s.camera, cams[v])
        expect = imgs[v, f].astype(np.float32) / 255.0
        assert torch.equal(s.image, torch.from_numpy(np.ascontiguousarray(expect[..., :3])))
        if alpha:
            assert torch.equal(s.alpha, torch.from_numpy(np.ascontiguousarray(expect[..., 3])))


def test_nerf_layout_round_trip(tmp_path, rng):
    cams, imgs = rig(), images(rng)
    times = np.arange(FRAMES) / FPS
    flat = [(imgs[v, f], cams[v], times[f], v) for f in range(FRAMES) for v in range(VIEWS)]
    write_nerf_dataset(tmp_path, "train", *zip(*flat), fps=FPS)
    ds = load_dataset(tmp_path)
    assert ds.meta["layout"] == "nerf" and ds.channels == 3
    check(ds, cams, imgs, times)


def test_nerf_camera_angle_x_and_implicit_views(tmp_path, rng):
    """Plain NeRF json: global camera_angle_x, no view_id, no w/h (taken from the PNG)."""
    cams, imgs = rig(), images(rng)
    frames = []
    for f in range(FRAMES):
        for v in range(VIEWS):
            write_png(tmp_path / f"r_{v}_{f}.png", imgs[v, f])
            frames.append({"file_path": f"./r_{v}_{f}", "time": f / FPS,
                           "transform_matrix": cams[v].to_blender_c2w().tolist()})
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": cams[0].camera_angle_x, "frames": frames}))
    ds = load_dataset(tmp_path)
    check(ds, cams, imgs, np.arange(FRAMES) / FPS)


def test_neurofluid_layout(tmp_path, rng):
    cams, imgs = rig(), images(rng)
    for v in range(VIEWS):
        d = tmp_path / f"view_{v}"
        frames = []
        for f in range(FRAMES):
            write_png(d / "train" / f"{f:03d}.png", imgs[v, f])
            frames.append({"file_path": f"train/{f:03d}", "particle_path": f"{f:03d}.pkl",
                           "transform_matrix": cams[v].to_blender_c2w().tolist()})
        (d / "transforms_train.json").write_text(
            json.dumps({"camera_angle_x": cams[v].camera_angle_x, "frames": frames}))
    ds = load_dataset(tmp_path, fps=FPS)
    assert ds.meta["layout"] == "neurofluid"
    check(ds, cams, imgs, np.arange(FRAMES) / FPS)
    # without fps: a one-second clip
    assert np.allclose(load_dataset(tmp_path).times, np.linspace(0, 1, FRAMES))


def write_video_layout(root, cams, imgs, fps=FPS, start=0.0, **extra):
    entries = []
    for v, cam in enumerate(cams):
        write_video(root / f"cam{v}.mkv", imgs[v], fps)
        entries.append({"video": f"cam{v}.mkv", "view_id": v,
                        "transform_matrix": cam.to_blender_c2w().tolist(), "fl_x": cam.fx,
                        "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, **extra})
    (root / "cameras.json").write_text(json.dumps({"cameras": entries, "start_time": start}))


def test_video_layout(tmp_path, rng):
    cams, imgs = rig(), images(rng, channels=3)
    write_video_layout(tmp_path, cams, imgs, start=0.5)
    ds = load_dataset(tmp_path)
    assert ds.meta["layout"] == "video"
    check(ds, cams, imgs, 0.5 + np.arange(FRAMES) / FPS, alpha=False)


def test_grayscale_background_removal(tmp_path, rng):
    cams = rig()
    bg = rng.integers(0, 120, size=(H, W), dtype=np.uint8)
    gray = np.repeat(bg[None, None], FRAMES, 1).repeat(VIEWS, 0)
    gray[:, 1:, 4:8, 5:9] += 100  # "smoke" appears after the first frame
    write_video_layout(tmp_path, cams, np.repeat(gray[..., None], 3, -1))
    ds = load_grayscale(tmp_path)
    assert ds.channels == 1
    s0, s2 = ds[ds.indices(view_id=1, time=0.0)[0]], ds[ds.indices(view_id=1, time=2 / FPS)[0]]
    assert s0.image.shape == (H, W, 1) and float(s0.image.abs().max()) == 0.0
    assert torch.allclose(s2.image[4:8, 5:9], torch.full((4, 4, 1), 100 / 255.0))
    assert float(s2.image[:4].abs().max()) == 0.0
    xor = load_grayscale(tmp_path, background_removal="xor")
    expect = np.bitwise_xor(gray[1, 2], gray[1, 0]).astype(np.float32) / 255.0
    assert np.array_equal(xor[xor.indices(view_id=1, time=2 / FPS)[0]].image[..., 0].numpy(), expect)


def test_ground_truth_particles_attached(tmp_path, rng):
    cams, imgs = rig(), images(rng)
    flat = [(imgs[v, 0], cams[v], 0.0, v) for v in range(VIEWS)]
    write_nerf_dataset(tmp_path, "train", *zip(*flat), extra={"gt_particles": "gt_sim.h5"})
    pos = rng.uniform(size=(1, 10, 3))
    write_sim(tmp_path / "gt_sim.h5", SimData(pos, np.zeros_like(pos), fps=FPS, particle_radius=0.01))
    gt = load_dataset(tmp_path).ground_truth()
    assert np.allclose(gt.positions, pos)


def test_lazy_start_is_fast(tmp_path, rng):
    """5 views x 100 frames x 400x400: opening must not decode anything."""
    cam = Camera.look_at([0, -3, 0], [0, 0, 0], [0, 0, 1], fx=400, width=400, height=400)
    img = np.zeros((400, 400, 4), np.uint8)
    write_png(tmp_path / "img.png", img)
    entries = [frame_entry("img.png", cam, f / 100.0, v) for f in range(100) for v in range(5)]
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": entries}))
    import cv2

    from gf_core.data import images as images_mod

    calls = []
    monkey = {"images": images_mod.read_image, "cv2": cv2.imread}
    images_mod.read_image = lambda *a, **k: calls.append("read_image") or monkey["images"](*a, **k)
    cv2.imread = lambda *a, **k: calls.append("imread") or monkey["cv2"](*a, **k)
    try:
        t0 = time.perf_counter()
        ds = load_dataset(tmp_path)
        elapsed = time.perf_counter() - t0
    finally:
        images_mod.read_image, cv2.imread = monkey["images"], monkey["cv2"]
    assert len(ds) == 500 and elapsed < 5.0, elapsed
    assert len(ds._cache) == 0 and calls == []  # no decode at all, by any path


def test_video_frames_are_read_by_seeking_not_whole_videos(tmp_path, rng):
    """Interleaved multiview access with a cache too small to hold the videos: each request
    decodes about one frame (it used to decode the whole video each time)."""
    cams = rig()
    n = 24
    imgs = rng.integers(0, 256, size=(VIEWS, n, H, W, 3), dtype=np.uint8)
    write_video_layout(tmp_path, cams, imgs)
    ds = load_dataset(tmp_path)
    ds.cache_bytes = 2 * H * W * 3  # two frames
    order = [(v, f) for f in range(0, n, 3) for v in range(VIEWS)] + [(v, f) for f in (20, 1, 13) for v in range(VIEWS)]
    for v, f in order:
        i = ds.indices(view_id=v, time=f / FPS)[0]
        img, _ = ds.load(i)
        assert np.array_equal((img * 255).round().astype(np.uint8), imgs[v, f])
    assert ds.frames_decoded == len(order)


def test_derived_datasets_share_the_open_videos(tmp_path, rng):
    """A dataset per frame (what a per-frame fit makes) opens no decoder of its own: however many
    datasets read the videos, at most MAX_OPEN_VIDEOS stay open, and a video replaced on disk is
    read anew."""
    from gf_core.data import dataset as dsmod

    cams = rig()
    imgs = rng.integers(0, 256, size=(VIEWS, FRAMES, H, W, 3), dtype=np.uint8)
    write_video_layout(tmp_path, cams, imgs)
    ds = load_dataset(tmp_path)
    dsmod._READERS.clear()
    for _ in range(20):
        for t in ds.times:
            one = ds.with_times([t])
            for i in range(len(one)):
                one.load(i)
    assert len(dsmod._READERS) == VIEWS <= dsmod.MAX_OPEN_VIDEOS
    write_video(tmp_path / "cam0.mkv", imgs[0][::-1], FPS)  # the same name, other frames
    fresh = load_dataset(tmp_path)
    i = fresh.indices(view_id=0, time=0.0)[0]
    assert np.array_equal((fresh.load(i)[0] * 255).round().astype(np.uint8), imgs[0][-1])


def test_intrinsics_and_fps_are_checked_alike_in_every_layout(tmp_path, rng):
    cams, imgs = rig(), images(rng, channels=3)
    write_video_layout(tmp_path / "v", cams, imgs[:, :2], camera_angle_x=3.5)
    meta = json.loads((tmp_path / "v" / "cameras.json").read_text())
    for c in meta["cameras"]:
        c.pop("fl_x"), c.pop("fl_y")
    (tmp_path / "v" / "cameras.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="camera_angle_x must be a field of view in \\(0, pi\\)"):
        load_dataset(tmp_path / "v")
    # NeuroFluid: a non-numeric fps, and an unknown background removal
    d = tmp_path / "nf" / "view_0"
    d.mkdir(parents=True)
    write_png(d / "a.png", imgs[0, 0])
    (d / "transforms_train.json").write_text(json.dumps({"fps": "fast", "frames": [frame_entry("a.png", cams[0], 0.0, 0)]}))
    with pytest.raises(InputError, match="'fps' must be a finite number, got 'fast'"):
        load_dataset(tmp_path / "nf")
    with pytest.raises(InputError, match="unknown method 'bogus'"):
        load_dataset(tmp_path / "nf", background_removal="bogus")


def test_wrong_size_jpeg_is_caught_without_decoding(tmp_path, rng):
    import cv2

    cams = rig()
    cv2.imwrite(str(tmp_path / "a.jpg"), np.zeros((H + 2, W, 3), np.uint8))
    fr = frame_entry("a.jpg", cams[0], 0.0, 0)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": [fr]}))
    with pytest.raises(InputError, match=f"image is {W}x{H + 2} but transforms_train.json says {W}x{H}"):
        load_dataset(tmp_path)
    (tmp_path / "a.jpg").write_bytes((tmp_path / "a.jpg").read_bytes()[:20])  # cut before its header
    with pytest.raises(InputError, match="no frame header"):
        load_dataset(tmp_path)


# ---- bad input: every error names the file and the problem --------------------------------------
def nerf_one(tmp_path, rng, **frame_overrides):
    cams, imgs = rig(), images(rng)
    write_png(tmp_path / "a.png", imgs[0, 0])
    fr = frame_entry("a.png", cams[0], 0.0, 0)
    fr.update(frame_overrides)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": [fr]}))
    return tmp_path / "transforms_train.json"


def test_missing_image(tmp_path, rng):
    nerf_one(tmp_path, rng, file_path="nope.png")
    with pytest.raises(InputError, match=r"nope.png: image listed in .*transforms_train.json does not exist"):
        load_dataset(tmp_path)


def test_wrong_image_size(tmp_path, rng):
    nerf_one(tmp_path, rng, w=W * 2)
    with pytest.raises(InputError, match=r"a.png: image is 24x16 but transforms_train.json says 48x16"):
        load_dataset(tmp_path)


def test_wrong_video_size(tmp_path, rng):
    cams, imgs = rig(), images(rng, channels=3)
    write_video_layout(tmp_path, cams, imgs, w=W, h=H)
    ds = load_dataset(tmp_path)
    assert ds[0].image.shape == (H, W, 3)
    write_video(tmp_path / "cam0.mkv", imgs[0, :, :8, :8], FPS)  # replaced with a smaller video
    with pytest.raises(InputError, match=r"cam0.mkv: video is 8x8 but cameras.json says 24x16"):
        load_dataset(tmp_path)


def test_malformed_json(tmp_path):
    (tmp_path / "transforms_train.json").write_text('{"frames": [ {"file_path": ')
    with pytest.raises(InputError, match=r"transforms_train.json: malformed JSON"):
        load_dataset(tmp_path)


def test_zero_focal_length(tmp_path, rng):
    nerf_one(tmp_path, rng, fl_x=0.0, fl_y=0.0)
    with pytest.raises(InputError, match=r"transforms_train.json: frame 0: focal length must be positive"):
        load_dataset(tmp_path)


def test_nan_in_pose(tmp_path, rng):
    path = nerf_one(tmp_path, rng)
    path.write_text(path.read_text().replace("[1.0,", "[NaN,", 1).replace("[0.0,", "[NaN,", 1))
    with pytest.raises(InputError, match=r"transforms_train.json: frame 0: 'transform_matrix' contains NaN or infinite values"):
        load_dataset(tmp_path)


def test_missing_time(tmp_path, rng):
    path = nerf_one(tmp_path, rng)
    meta = json.loads(path.read_text())
    del meta["frames"][0]["time"]
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="frame 0: no 'time'"):
        load_dataset(tmp_path)


def test_corrupt_image_and_video(tmp_path, rng):
    nerf_one(tmp_path, rng)
    (tmp_path / "a.png").write_bytes(b"\x89PNG garbage")
    ds = load_dataset(tmp_path, )
    with pytest.raises(InputError, match=r"a.png: cannot decode image"):
        ds[0]
    (tmp_path / "cameras.json").write_text(json.dumps({"cameras": [{"video": "v.mkv", "fl_x": 10,
                                                                    "transform_matrix": np.eye(4).tolist()}]}))
    (tmp_path / "v.mkv").write_bytes(b"garbage")
    with pytest.raises(InputError, match=r"v.mkv: OpenCV cannot open this video"):
        load_dataset(tmp_path, layout="video")


def test_unknown_layout_and_missing_folder(tmp_path):
    with pytest.raises(InputError, match="no known dataset layout"):
        load_dataset(tmp_path)
    with pytest.raises(InputError, match="dataset folder does not exist"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(ValueError, match="unknown dataset layout 'llff'"):
        load_dataset(tmp_path, layout="llff")


def test_inspect_checks_what_it_claims(tmp_path, rng, capsys):
    """Without --decode, inspect still catches a truncated gt_sim.h5 and a truncated video."""
    from gf_cli.main import main

    cams, imgs = rig(), images(rng)
    write_nerf_dataset(tmp_path / "n", "train", [imgs[v, f] for v in range(VIEWS) for f in range(FRAMES)],
                       [cams[v] for v in range(VIEWS) for f in range(FRAMES)],
                       [f / FPS for v in range(VIEWS) for f in range(FRAMES)],
                       [v for v in range(VIEWS) for f in range(FRAMES)])
    sim = SimData(positions=np.zeros((2, 3, 3)), velocities=np.zeros((2, 3, 3)), fps=FPS, particle_radius=0.01)
    write_sim(tmp_path / "n" / "gt_sim.h5", sim)
    assert main(["inspect", str(tmp_path / "n")]) == 0
    data = (tmp_path / "n" / "gt_sim.h5").read_bytes()
    (tmp_path / "n" / "gt_sim.h5").write_bytes(data[: len(data) // 2])
    assert main(["inspect", str(tmp_path / "n")]) == 2
    assert "gt_sim.h5" in capsys.readouterr().err
    write_video_layout(tmp_path / "v", cams, images(rng, channels=3))
    assert main(["inspect", str(tmp_path / "v")]) == 0
    video = tmp_path / "v" / "cam1.mkv"
    data = video.read_bytes()
    video.write_bytes(data[: int(len(data) * 0.6)])
    capsys.readouterr()
    assert main(["inspect", str(tmp_path / "v")]) == 2
    assert "cam1.mkv" in capsys.readouterr().err


# ---- lens distortion (nerfstudio's transforms.json) ----------------------------------------------
@pytest.mark.parametrize("model, coeffs", [
    ("OPENCV", {"k1": -0.35, "k2": 0.08, "p1": 0.004, "p2": -0.003}),
    ("OPENCV_FISHEYE", {"k1": 0.09, "k2": -0.02, "k3": 0.01, "k4": -0.004}),
])
def test_distorted_images_load_as_the_pinhole_images_of_their_camera(tmp_path, model, coeffs):
    """A nerfstudio transforms.json with per-frame intrinsics and a lens model: dots recorded where
    the lens puts known 3D points land, once loaded, where the pinhole camera projects those points
    (within 0.15 px), though the lens moved them by up to several pixels."""
    from gf_core.data.distortion import Distortion, MODELS

    w, h = 96, 72
    cam = Camera(80.0, 78.0, 50.3, 34.1, w, h,
                 Camera.look_at([0.3, -2.0, 0.6], [0, 0, 0], [0, 0, 1], fx=80.0, width=w, height=h).world_to_camera)
    lens = Distortion(model, tuple(coeffs.get(k, 0.0) for k in MODELS[model]))
    # 3D points whose pinhole projections form a grid, 2 m in front of the camera
    gu, gv = np.meshgrid(np.linspace(12, w - 12, 5), np.linspace(12, h - 12, 4))
    uv = np.stack([gu.ravel(), gv.ravel()], 1)
    rays = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))], 1)
    pts = (rays * 2.0 - cam.world_to_camera[:3, 3]) @ cam.world_to_camera[:3, :3]
    proj, _ = cam.project(pts)
    np.testing.assert_allclose(proj, uv, atol=1e-9)
    xd, yd = lens.distort((proj[:, 0] - cam.cx) / cam.fx, (proj[:, 1] - cam.cy) / cam.fy)
    rec = np.stack([xd * cam.fx + cam.cx, yd * cam.fy + cam.cy], 1)  # where the recording shows them
    assert np.abs(rec - proj).max() > 2.5
    yy, xx = np.mgrid[0:h, 0:w] + 0.5  # pixel centres
    img = sum(np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 1.3 ** 2)) for u, v in rec)
    write_png(tmp_path / "r.png", np.repeat(np.clip(img, 0, 1)[..., None], 3, 2))
    frame = {"file_path": "r.png", "transform_matrix": cam.to_blender_c2w().tolist(), "time": 0.0,
             "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": w, "h": h}
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_model": model, **coeffs, "frames": [frame]}))
    s = load_dataset(tmp_path)[0]
    assert s.camera.allclose(cam, atol=1e-9)
    got = s.image[..., 0].numpy()
    for u, v in np.rint(proj).astype(int):  # the intensity centroid of the 6 x 6 pixels centred on each projection
        win = (slice(v - 3, v + 3), slice(u - 3, u + 3))
        c = np.array([(got[win] * xx[win]).sum(), (got[win] * yy[win]).sum()]) / got[win].sum()
        assert np.abs(c - (u, v)).max() < 0.15, (u, v, c)


def test_lens_keys_are_checked(tmp_path, rng):
    cams, imgs = rig(), images(rng)
    write_png(tmp_path / "r.png", imgs[0, 0])
    base = {"file_path": "r.png", "transform_matrix": cams[0].to_blender_c2w().tolist(), "time": 0.0, "fl_x": 20.0}
    for extra, msg in (({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
                       ({"camera_model": "OPENCV", "k4": 0.1}, "k4 are not coefficients of camera_model OPENCV"),
                       ({"k1": "big"}, "distortion coefficient k1 must be a finite number"),
                       ({"camera_model": "PINHOLE", "k1": 0.2}, "has no distortion")):
        (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": [{**base, **extra}]}))
        with pytest.raises(InputError, match=msg):
            load_dataset(tmp_path)
    # all-zero coefficients and a pinhole model: the images as recorded
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": [base]}))
    assert load_dataset(tmp_path).frames[0].distortion is None


# ---- COLMAP rigs (sparse model + one video per camera) --------------------------------------------
def write_colmap_rig(root, cams, imgs, *, binary=True, model="PINHOLE", extra=()):
    from gf_core.data.colmap import write_rig

    for v in range(len(cams)):
        write_video(root / f"cam{v:02d}.mkv", imgs[v], FPS)
    params = [(c.fx, c.fy, c.cx, c.cy) + tuple(extra) for c in cams]
    # listed in the file in reverse: the views follow the images' names, not the file's order
    write_rig(root / "sparse/0", cams[::-1], [f"cam{v:02d}.png" for v in range(len(cams))][::-1], binary=binary,
              params=params[::-1], model=model)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_layout(tmp_path, rng, binary):
    """A COLMAP sparse model of the rig (world-to-camera quaternions, PINHOLE intrinsics) and one
    video per registered image: the cameras are the rig's own, views in the images' name order,
    frames at k / fps; a point projects where the rig's camera projects it."""
    cams, imgs = rig(), images(rng, channels=3)
    write_colmap_rig(tmp_path, cams, imgs, binary=binary)
    ds = load_dataset(tmp_path)
    assert ds.meta["layout"] == "colmap"
    check(ds, cams, imgs, np.arange(FRAMES) / FPS, alpha=False)
    pts = np.array([[0.1, -0.2, 0.05], [-0.3, 0.1, 0.2]])
    for v in range(VIEWS):
        s = ds[ds.indices(view_id=v, time=0.0)[0]]
        np.testing.assert_allclose(s.camera.project(pts)[0], cams[v].project(pts)[0], atol=1e-9)
    assert len(load_dataset(tmp_path, fps=10.0).times) == FRAMES
    assert np.allclose(load_dataset(tmp_path, fps=10.0).times, np.arange(FRAMES) / 10.0)  # --fps overrides the video's


def test_colmap_lens_model_and_bad_models(tmp_path, rng):
    from gf_core.data.colmap import write_model

    cams, imgs = rig(), images(rng, channels=3)
    write_colmap_rig(tmp_path, cams, imgs, model="OPENCV", extra=(-0.2, 0.05, 0.001, -0.002))
    f = load_dataset(tmp_path).frames[0]
    assert f.distortion.model == "OPENCV" and f.distortion.coeffs[:4] == (-0.2, 0.05, 0.001, -0.002)
    # a missing video, an unknown camera, a truncated file, a wrong parameter count: one line each
    (tmp_path / "cam01.mkv").unlink()
    with pytest.raises(InputError, match=r"no video for COLMAP image 'cam01.png'"):
        load_dataset(tmp_path)
    write_video(tmp_path / "cam01.mkv", imgs[1], FPS)
    data = (tmp_path / "sparse/0/images.bin").read_bytes()
    (tmp_path / "sparse/0/images.bin").write_bytes(data[: len(data) - 30])
    with pytest.raises(InputError, match=r"images.bin.*truncated"):
        load_dataset(tmp_path)
    write_model(tmp_path / "sparse/0", {1: ("PINHOLE", W, H, (20.0, 20.0, 12.0, 8.0))},
                [(1, (1.0, 0, 0, 0), (0, 0, 2.0), 7, "cam00.png")])
    with pytest.raises(InputError, match="refers to camera 7"):
        load_dataset(tmp_path)
    (tmp_path / "sparse/0/cameras.bin").unlink()
    (tmp_path / "sparse/0/images.bin").unlink()
    write_model(tmp_path / "sparse/0", {1: ("PINHOLE", W, H, (20.0, 20.0, 12.0, 8.0))},
                [(1, (1.0, 0, 0, 0), (0, 0, 2.0), 1, "cam00.png")], binary=False)
    (tmp_path / "sparse/0/cameras.txt").write_text("1 PINHOLE 24 16 20.0 20.0 12.0\n")
    with pytest.raises(InputError, match="PINHOLE has 4 parameters, got 3"):
        load_dataset(tmp_path)
    (tmp_path / "sparse/0/cameras.txt").write_text("1 THIN_PRISM_FISHEYE 24 16 20.0 20.0 12.0 8.0\n")
    with pytest.raises(InputError, match="camera model 'THIN_PRISM_FISHEYE' is not one of"):
        load_dataset(tmp_path)
