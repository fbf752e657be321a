"""Dataset rendering with Blender (bpy module): 5 views x 3 frames at 64x64, loaded back."""

import importlib.util
import json

import numpy as np
import pytest

from gf_core.data import load_dataset
from helpers import assert_same_render
from gf_core.formats.hdf5 import read_sim, write_sim
from gf_core.sim import simulate

pytestmark = [pytest.mark.blender,
              pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy not installed")]


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory):
    sim, _ = simulate("water_sphere", particles=600, fps=20, seconds=0.2)
    path = tmp_path_factory.mktemp("sim") / "sim.h5"
    write_sim(path, sim)
    return path


def render(sim_file, out, *extra):
    from gf_cli.main import main

    assert main(["render-dataset", str(sim_file), "--out", str(out), "--resolution", "64",
                 "--samples", "4", "--frames", "0:5:2", *extra]) == 0


def test_render_and_load_back(sim_file, tmp_path, capsys):
    out = tmp_path / "ds"
    render(sim_file, out, "--test-views", "1")
    ds = load_dataset(out)
    sim = read_sim(sim_file)
    assert len(ds) == 15 and ds.views == [0, 1, 2, 3, 4]
    assert np.allclose(ds.times, sim.times[[0, 2, 4]])
    assert ds.ground_truth().num_particles == sim.num_particles
    test = load_dataset(out, split="test")
    assert len(test) == 3 and test.views == [5]  # held-out cameras are numbered after the training ones
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["blender"].startswith(("4.", "5.")) and manifest["options"]["seed"] == 0
    cams = ds.cameras()
    assert len({tuple(np.round(c.center, 6)) for c in cams.values()}) == 5
    for view in ds.views:
        imgs = []
        for fi, t in zip([0, 2, 4], ds.times):
            s = ds[ds.indices(view_id=view, time=t)[0]]
            assert s.image.shape == (64, 64, 3) and s.alpha is not None
            # the cameras in the json agree with Blender's: particles project onto fluid pixels
            uv, z = s.camera.project(sim.positions[fi])
            assert np.all(z > 0)
            px = np.clip(np.floor(uv).astype(int), 0, 63)
            covered = s.alpha.numpy()[px[:, 1], px[:, 0]] > 0.5
            assert covered.mean() > 0.9, (view, fi, covered.mean())
            assert 0.01 < float(s.alpha.mean()) < 0.6  # visible, and not the whole frame
            imgs.append(s.image.numpy())
        assert np.abs(imgs[0] - imgs[2]).mean() > 1e-3  # the fluid moved between frames


def test_resumable_and_deterministic(sim_file, tmp_path, capsys):
    out = tmp_path / "ds"
    render(sim_file, out)
    import cv2

    first = cv2.imread(str(out / "train" / "v02_f00002.png"), cv2.IMREAD_UNCHANGED)
    (out / "train" / "v02_f00002.png").unlink()
    capsys.readouterr()
    render(sim_file, out)  # only the missing image is rendered again (the log says so; no wall-time test)
    log = capsys.readouterr().out
    assert "frame 1/3 (sim frame 0): already rendered, skipped" in log
    assert "frame 2/3 (sim frame 2, t = 0.100 s): 1 images" in log
    assert "frame 3/3 (sim frame 4): already rendered, skipped" in log
    again = cv2.imread(str(out / "train" / "v02_f00002.png"), cv2.IMREAD_UNCHANGED)
    assert_same_render(again, first)
    assert not list(out.rglob("*.partial*"))
    # a torn image (a full disk or an interrupted copy: the header is there, the pixels are not)
    torn = out / "train" / "v03_f00004.png"
    torn.write_bytes(torn.read_bytes()[:60])
    capsys.readouterr()
    render(sim_file, out)
    log = capsys.readouterr().out
    assert "frame 3/3 (sim frame 4, t = 0.200 s): 1 images" in log and "frame 2/3 (sim frame 2): already" in log
    assert cv2.imread(str(torn), cv2.IMREAD_UNCHANGED).shape == (64, 64, 4)


def test_killed_anywhere_resumes_to_the_uninterrupted_images(sim_file, tmp_path):
    """SIGKILL once the first frame's images and a random number of the later ones are written
    (the kill lands while the next one renders or is written), then the same command: the frames
    already there are skipped, the rest rendered; every image decodes at its size and matches an
    uninterrupted render's (same seed), and no partial file is left. Counting images, not
    seconds, puts the kill inside the render on a machine of any speed."""
    import random
    import signal
    import subprocess
    import sys
    import time

    import cv2

    args = ["render-dataset", str(sim_file), "--resolution", "64", "--samples", "64", "--frames", "0:5:2"]
    render(sim_file, tmp_path / "a", "--samples", "64")
    ref = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*.png"))
    assert len(ref) == 15  # 5 views x 3 frames
    out = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "gf_cli.main", *args, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    kill_after = random.Random(1).randint(5, len(ref) - 2)  # images written before the kill
    while len(list((out / "train").glob("*.png"))) < kill_after:
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < 300
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(list(out.rglob("*.png"))) < len(ref), "the render ended before the kill; the test needs a longer one"
    again = subprocess.run([sys.executable, "-m", "gf_cli.main", *args, "--out", str(out)],
                           capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert "frame 1/3 (sim frame 0): already rendered, skipped" in again.stdout + again.stderr
    assert sorted(p.relative_to(out) for p in out.rglob("*.png")) == ref
    for rel in ref:
        a = cv2.imread(str(tmp_path / "a" / rel), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(out / rel), cv2.IMREAD_UNCHANGED)
        assert b is not None and b.shape == a.shape == (64, 64, 4), rel
        assert_same_render(b, a, rel)
    assert not list(out.rglob("*.partial*"))
    fa, fb = (json.loads((d / "transforms_train.json").read_text())["frames"] for d in (tmp_path / "a", out))
    assert [{k: v for k, v in f.items() if k != "transform_matrix"} for f in fb] == \
        [{k: v for k, v in f.items() if k != "transform_matrix"} for f in fa]
    # the cameras: equal up to float32 rounding (Blender's matrix_world of a scene built again)
    assert np.allclose([f["transform_matrix"] for f in fb], [f["transform_matrix"] for f in fa], atol=1e-6)


def test_resume_refuses_another_simulation(sim_file, tmp_path, capsys):
    """Rendering simulation B into a folder made from simulation A is refused (it used to skip
    every frame and keep A's images under B's manifest); --force starts afresh."""
    from gf_cli.main import main

    out = tmp_path / "ds"
    render(sim_file, out, "--views", "2", "--frames", "0:1")
    other, _ = simulate("honey_cone", particles=500, fps=20, seconds=0.1)
    b = tmp_path / "b.h5"
    write_sim(b, other)
    capsys.readouterr()
    assert main(["render-dataset", str(b), "--out", str(out), "--resolution", "64", "--samples", "4",
                 "--views", "2", "--frames", "0:1"]) == 2
    err = capsys.readouterr().err + capsys.readouterr().out
    assert "made from something else" in err and "the simulation differs" in err
    assert main(["render-dataset", str(sim_file), "--out", str(out), "--resolution", "32", "--samples", "4",
                 "--views", "2", "--frames", "0:1"]) == 2  # other options: refused too
    assert "--resolution 64 here, 32 given" in capsys.readouterr().err
    render(b, out, "--views", "2", "--frames", "0:1", "--force")
    assert read_sim(out / "gt_sim.h5").num_particles == other.num_particles
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["source"]["options"]["material"] == "auto" and manifest["material"] == "honey"


def test_bad_inputs(sim_file, tmp_path):
    from gf_cli.main import main

    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    assert main(["render-dataset", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert main(["render-dataset", str(sim_file), "--out", str(tmp_path / "y"), "--blender",
                 str(tmp_path / "no-blender")]) == 2


@pytest.mark.parametrize("material", ["honey", "smoke"])
def test_other_materials_render(sim_file, tmp_path, material):
    out = tmp_path / material
    render(sim_file, out, "--material", material, "--views", "2", "--frames", "2:3")
    ds = load_dataset(out)
    s = ds[0]
    assert float(s.alpha.mean()) > 0.01
    if material == "honey":  # amber: more red than blue where the fluid is
        m = s.alpha > 0.5
        assert float(s.image[..., 0][m].mean()) > float(s.image[..., 2][m].mean())


def test_blender_binary_path_uses_npz(sim_file, tmp_path):
    """With a `blender` executable, gf-cli hands it the particles as .npz (Blender's own Python
    may lack h5py) and Blender's command line (-b -P script -- args). A stand-in executable that
    runs the script with this Python's bpy checks that path end to end."""
    import sys

    fake = tmp_path / "blender"
    fake.write_text(
        f"#!{sys.executable}\n"
        "import runpy, sys\n"
        "argv = sys.argv[1:]\n"
        "assert argv[:2] == ['-b', '--factory-startup'] and '-P' in argv and '--' in argv, argv\n"
        "sys.modules['h5py'] = None  # as in a stock Blender without h5py\n"
        "script = argv[argv.index('-P') + 1]\n"
        "sys.argv = [script] + argv[argv.index('--') + 1:]\n"
        "runpy.run_path(script, run_name='__main__')\n")
    fake.chmod(0o755)
    out = tmp_path / "ds"
    render(sim_file, out, "--blender", str(fake), "--views", "2", "--frames", "0:1")
    ds = load_dataset(out)
    assert len(ds) == 2 and ds.gt_file is not None and ds.ground_truth().num_particles > 0


def test_clear_message_without_h5py(sim_file, tmp_path):
    import subprocess
    import sys

    from gf_cli.cmd_render_dataset import script_path

    code = ("import sys, runpy; sys.modules['h5py'] = None; "
            f"sys.argv = ['x', '--sim', {str(sim_file)!r}, '--out', {str(tmp_path / 'o')!r}]; "
            f"runpy.run_path({str(script_path())!r}, run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode != 0
    assert "h5py is not importable" in r.stderr and "gf-cli render-dataset" in r.stderr
