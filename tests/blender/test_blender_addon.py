"""The Blender extension under the bpy module: built zip, installed as a user installs it, a
reconstruction imported, frames and sub-frames equal to the torch decoder, two looks rendered,
USD and OpenVDB bakes read back, a saved scene re-opened and rendered as `blender -b -a` does,
and the training-dataset operator."""

import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from gf_core.formats.decoder_np import ParticleAnimation
from gf_core.formats.hdf5 import ReconData, read_recon, write_recon, write_sim
from gf_core.recon.decoder import Decoder, DecoderConfig

pytestmark = [pytest.mark.blender,
              pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy not installed")]

DRIVER = Path(__file__).with_name("addon_driver.py")
FPS, T_MAX = 24, 0.5
DRIFT = 0.6  # m/s along +x: the decoder's last-layer bias, so the fluid visibly moves


@pytest.fixture(scope="module")
def addon_zip(tmp_path_factory):
    from gf_cli.cmd_addon import PLATFORMS, build

    cache = Path(os.environ.get("GF_WHEEL_CACHE", Path.home() / ".cache" / "gaussfluids" / "wheels"))
    return build(tmp_path_factory.mktemp("dist"), list(PLATFORMS), cache)


@pytest.fixture(scope="module")
def recon_file(tmp_path_factory):
    """300 particles in a ball with a random decoder (non-zero everywhere) plus a drift, and a
    base colour that changes in time (colour residuals at 6 knots)."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n = 300
    dec = Decoder(n, DecoderConfig(residuals=True, color_residuals=True), knots=np.linspace(0.0, 1.0, 6), channels=3)
    with torch.no_grad():
        dec.residual_dc.normal_(0.0, 0.5)
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
        dec.layers[-1].bias[0] = DRIFT * T_MAX  # Delta p = tau * (... + DRIFT * T_MAX)
    dirs = rng.normal(size=(n, 3))
    means = (0.1 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.random((n, 1)) ** (1 / 3)
             + [0.0, 0.0, 0.3]).astype(np.float32)
    sh = np.zeros((n, 4, 3), np.float32)
    sh[:, 0, :] = rng.normal(0.0, 1.0, (n, 3))
    r = ReconData(means=means, log_scales=np.full((n, 3), np.log(0.015), np.float32),
                  quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), logit_opacity=np.full(n, 2.0, np.float32),
                  sh=sh, time_min=0.0, time_max=T_MAX, decoder=dec.to_data(),
                  metrics={"iterations": 0, "note": "random decoder for tests"})
    path = tmp_path_factory.mktemp("recon") / "recon.h5"
    write_recon(path, r)
    return path


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    from gf_core.sim import simulate

    sim, _ = simulate("water_sphere", particles=300, fps=20, seconds=0.1)
    path = tmp_path_factory.mktemp("sim") / "sim.h5"
    write_sim(path, sim)
    return path


def drive(zip_path, recon, out, steps, home, python=sys.executable):
    """Run the extension driver with ``python`` (an interpreter with the bpy module) on ``steps``."""
    job = out / "job.json"
    out.mkdir(parents=True, exist_ok=True)
    job.write_text(json.dumps({"zip": str(zip_path), "recon": str(recon), "out": str(out), "steps": steps}))
    env = dict(os.environ, HOME=str(home))
    r = subprocess.run([str(python), str(DRIVER), str(job)], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
    return json.loads((out / "result.json").read_text()), r.stdout


CAM = {"eye": [0.15, -0.9, 0.4], "target": [0.15, 0.0, 0.3]}


@pytest.fixture(scope="module")
def exported_vdb(recon_file, tmp_path_factory):
    """``gf-cli export --format vdb`` of the first frame."""
    from gf_cli.main import main

    out = tmp_path_factory.mktemp("vdb")
    assert main(["export", str(recon_file), "--format", "vdb", "--frames", "0:1", "--out", str(out)]) == 0
    (path,) = sorted(out.glob("*.vdb"))
    return path


@pytest.fixture(scope="module")
def driven(addon_zip, recon_file, sim_file, exported_vdb, tmp_path_factory):
    out = tmp_path_factory.mktemp("addon")
    steps = [{"do": "import", "fps": FPS, "frame_end": 10},
             {"do": "frames", "frames": [1, 2, 3.5, 7.25, 30]},
             {"do": "render", "preset": "water", "frames": [1, 9], "camera": CAM, "res": 32, "samples": 4},
             {"do": "render", "preset": "glow", "frames": [1, 9], "camera": CAM, "res": 32, "samples": 4},
             {"do": "render", "preset": "smoke", "frames": [1], "camera": CAM, "res": 32, "samples": 4},
             {"do": "render", "preset": "honey", "frames": [1], "camera": CAM, "res": 32, "samples": 4},
             {"do": "render", "preset": "recon", "frames": [1], "camera": CAM, "res": 32, "samples": 4},
             {"do": "volume_import", "path": str(exported_vdb), "frame": 1},
             {"do": "save"},
             {"do": "bake_vdb"},
             {"do": "bake_usd", "substeps": 2, "replace": True},
             {"do": "open_and_render", "blend": str(out / "scene.blend"), "object": "gf_recon", "frames": [2, 3, 4, 5, 6]},
             {"do": "dataset", "sim": str(sim_file)},
             {"do": "import_bad", "path": str(out / "frames.npz")}]
    res, log = drive(addon_zip, recon_file, out, steps, out / "home")
    return res, log, out


def torch_positions(recon_file, t):
    r = read_recon(recon_file)
    dec = Decoder.from_data(r.decoder)
    tau = min(max(t / T_MAX, 0.0), 1.0)
    with torch.no_grad():
        d = dec(tau, with_velocity=True)
    v = d["vp"].numpy() / T_MAX if 0 <= t <= T_MAX else np.zeros((r.num_particles, 3))
    return r.means + d["dp"].numpy(), r.log_scales + d["ds"].numpy(), v


def test_zip_is_an_extension_for_four_platforms(addon_zip):
    import tomllib

    with zipfile.ZipFile(addon_zip) as z:
        names = z.namelist()
        man = tomllib.loads(z.read("blender_manifest.toml").decode())
        sources = {n: z.read(n).decode() for n in names if n.endswith(".py")}
    assert man["id"] == "gaussfluids" and man["blender_version_min"] == "4.5.0" and man["type"] == "add-on"
    assert set(man["platforms"]) == {"linux-x64", "macos-arm64", "macos-x64", "windows-x64"}
    # h5py for each platform and each Python Blender ships (3.11: 4.5 - 5.0; 3.13: 5.1 on)
    assert len(man["wheels"]) == 8 and all(w[2:] in names for w in man["wheels"])
    assert sum("-cp311-" in w for w in man["wheels"]) == sum("-cp313-" in w for w in man["wheels"]) == 4
    assert "files" in man["permissions"]
    for name, text in sources.items():
        assert "import torch" not in text and "from torch" not in text, name
    assert {"gf_core/formats/decoder_np.py", "gf_core/formats/hdf5.py", "gf_core/formats/__init__.py", "gf_core/errors.py",
            "render_data/scene_builder.py", "__init__.py"} <= set(names)


def test_zip_passes_blenders_own_extension_validate(addon_zip):
    """`blender --command extension validate`, run from the validator the bpy module bundles
    (e.g. a permission's reason is at most 64 characters)."""
    import bpy

    ext = Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    assert ext.exists(), f"the bpy module bundles no extension validator ({ext})"
    r = subprocess.run([sys.executable, str(ext), "validate", str(addon_zip)], capture_output=True, text=True)
    assert r.returncode == 0 and "Success" in r.stdout, r.stdout + r.stderr


def test_import_follows_the_decoder_at_frames_and_subframes(driven, recon_file):
    res, log, out = driven
    assert res["import"] == ["FINISHED"] and res["type"] == "POINTCLOUD" and res["lock_interface"]
    assert res["mapping"] == {"fps": FPS, "start_frame": 1.0, "speed": 1.0}
    got = np.load(out / "frames.npz")
    for f in (1, 2, 3.5, 7.25, 30):
        t = (f - 1) / FPS
        p, ls, v = torch_positions(recon_file, t)
        np.testing.assert_allclose(got[f"p_{f}"], p, atol=1e-5, err_msg=f"frame {f}")
        np.testing.assert_allclose(got[f"r_{f}"], 1.5 * np.exp(ls.mean(1)), rtol=1e-5)
        dv = np.abs(got[f"v_{f}"] - v).max(1)
        assert np.sum(dv > 1e-4) <= 1, (f, dv.max())  # a ReLU kink may differ in one particle
        # the reconstructed colour follows the colour residuals
        want = ParticleAnimation(read_recon(recon_file)).at(t, warn=False)["colors"]
        np.testing.assert_allclose(got[f"c_{f}"][:, :3], want, atol=1e-5, err_msg=f"colour at frame {f}")
    assert np.abs(got["c_2"] - got["c_7.25"]).max() > 0.05
    # frame 30 is past the clip: clamped to its end, velocity 0, and said so
    assert "outside the reconstruction" in log
    assert not got["v_30"].any()


def _load(path):
    import cv2

    return cv2.imread(str(path))[:, :, ::-1].astype(np.float64)


def test_two_looks_render_differently_and_the_fluid_moves(driven):
    _, _, out = driven
    w1, w9, g1, g9 = (_load(out / n) for n in ("water_1.png", "water_9.png", "glow_1.png", "glow_9.png"))
    bg = np.median(np.concatenate([w1.reshape(-1, 3), g1.reshape(-1, 3)]), 0)
    fluid_w1 = np.abs(w1 - bg).max(-1) > 12
    fluid_g1 = np.abs(g1 - bg).max(-1) > 12
    assert 0.02 < fluid_g1.mean() < 0.8 and fluid_w1.mean() > 0.02
    # different looks: large differences where the fluid is, none far from it
    fluid = fluid_w1 | fluid_g1
    assert np.abs(w1 - g1).max(-1)[fluid].mean() > 25
    assert np.abs(w1 - g1).max(-1)[~fluid].mean() < 6
    # the fluid drifts along +x, i.e. to the right in this camera, between frames 1 and 9
    cols = np.arange(w1.shape[1])

    def centre_x(img):
        mask = np.abs(img - bg).max(-1) > 12
        return (mask * cols).sum() / mask.sum()

    for a, b in ((g1, g9), (w1, w9)):
        assert centre_x(b) - centre_x(a) > 3.0, (centre_x(a), centre_x(b))


def test_every_other_look_renders_the_fluid(driven):
    _, _, out = driven
    w1 = _load(out / "water_1.png")
    bg = np.median(w1.reshape(-1, 3), 0)
    for look in ("smoke", "honey", "recon"):
        img = _load(out / f"{look}_1.png")
        fluid = np.abs(img - bg).max(-1) > 12
        assert 0.01 < fluid.mean() < 0.9, (look, fluid.mean())
        assert np.abs(img - w1).max(-1).mean() > 1.0, look  # not the water look again


def test_usd_bake_reloads_with_identical_positions(driven):
    res, _, out = driven
    assert res["bake_usd"] == ["FINISHED"]
    assert res["usd_frames"][:3] == [1.0, 1.5, 2.0] and len(res["usd_frames"]) == 19
    d = np.load(out / "usd.npz")
    for f in res["usd_frames"]:
        np.testing.assert_array_equal(d[f"usd_{f}"], d[f"live_{f}"])
    # "use the cache": Blender's own USD importer gives the same points, and the live object stops
    assert res["usd_objects"] and res["live_after_replace"] is False
    imp = np.load(out / "usd_imported.npz")
    for f in (2, 5):
        np.testing.assert_allclose(imp[f"imported_{f}"], d[f"usd_{float(f)}"], atol=1e-6)


def test_vdb_bake_writes_a_density_grid_per_frame(driven, recon_file):
    res, _, _ = driven
    assert res["bake_vdb"] == ["FINISHED"]
    assert res["vdb_files"] == ["density_00001.vdb", "density_00002.vdb"]
    assert res["vdb_active"] > 1000 and res["vdb_minmax"][1] > 1.0
    p, _, _ = torch_positions(recon_file, 0.0)
    np.testing.assert_allclose(res["vdb_centre"], p.mean(0), atol=0.05)


def test_exported_vdb_shows_as_smoke_through_blenders_volume_import(driven, recon_file):
    """`gf-cli export --format vdb` read by Blender's own OpenVDB import: a 'density' grid around the
    particles that the smoke material renders where the extension's smoke look puts the fluid."""
    res, _, out = driven
    assert res["volume_import"] == ["FINISHED"] and "density" in res["volume_grids"]
    p, _, _ = torch_positions(recon_file, 0.0)
    lo, hi = np.array(res["volume_bounds"])
    assert np.all(lo <= p.min(0)) and np.all(hi >= p.max(0)), (lo, hi, p.min(0), p.max(0))
    assert np.all(hi - lo < 1.5 * (p.max(0) - p.min(0)) + 0.1)
    bg = np.median(_load(out / "water_1.png").reshape(-1, 3), 0)
    vdb = np.abs(_load(out / "vdb_import.png") - bg).max(-1) > 12
    look = np.abs(_load(out / "smoke_1.png") - bg).max(-1) > 12
    assert 0.01 < vdb.mean() < 0.9, vdb.mean()
    assert (vdb & look).sum() / (vdb | look).sum() > 0.5, ((vdb & look).sum(), (vdb | look).sum())


def test_saved_scene_renders_the_animation_after_reopening(driven, recon_file):
    """What `blender -b scene.blend -a` does: the persistent handler moves the points per frame."""
    _, _, out = driven
    got = np.load(out / "reopened.npz")
    for f in (2, 3, 4, 5, 6):
        p, _, _ = torch_positions(recon_file, (f - 1) / FPS)
        np.testing.assert_allclose(got[f"p_{f}"], p, atol=1e-5)
    frames = [_load(out / f"anim_{f:04d}.png") for f in (2, 6)]
    assert np.abs(frames[1] - frames[0]).max(-1).mean() > 1.0


def test_dataset_operator_renders_with_render_data(driven, sim_file):
    from gf_core.data import load_dataset

    res, _, out = driven
    assert res["dataset"] == ["FINISHED"]
    ds = out / "dataset"
    assert (ds / "gt_sim.h5").read_bytes() == Path(sim_file).read_bytes()
    man = json.loads((ds / "manifest.json").read_text())
    assert man["generator"].startswith("gaussfluids render_data") and man["frames"] == [0, 1]
    train = load_dataset(ds, split="train")
    test = load_dataset(ds, split="test")
    assert len(train) == 2 and len(test) == 2


def test_a_broken_file_gives_an_error_naming_it(driven):
    res, _, out = driven
    assert isinstance(res["bad"], str)  # the operator reported an error (raised in background mode)
    assert str(out / "frames.npz") in res["bad"] and "not a readable HDF5 file" in res["bad"]
