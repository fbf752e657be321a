"""The gf-cli entry point: every command has --help; the demo runs end to end on tiny settings."""

import importlib.util
import json
import subprocess
import sys

import pytest

from gf_cli.main import COMMANDS, build_parser, main

EXPECTED = {"demo", "simulate", "render-dataset", "reconstruct", "evaluate", "predict", "edit", "inspect", "bench",
            "export", "addon", "batch"}


def test_help_lists_commands_and_each_has_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(c in out for c in EXPECTED)
    for cmd in EXPECTED | {"bench render", "bench sim", "bench reconstruct", "bench gpu", "bench decoder",
                            "addon build"}:
        with pytest.raises(SystemExit) as e:
            main(cmd.split() + ["--help"])
        assert e.value.code == 0
        assert "usage: gf-cli" in capsys.readouterr().out
    assert len(COMMANDS) == len(EXPECTED)


def test_console_script_installed():
    r = subprocess.run([sys.executable, "-m", "gf_cli.main", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "render-dataset" in r.stdout


def test_errors_name_the_problem(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "lava", "--out", "x.h5"])


def test_demo_quick_runs_every_stage_and_writes_a_self_contained_report(tmp_path, capsys):
    """``gf-cli demo --quick``: every stage at tiny sizes (Blender included), the report's images
    embedded and non-trivial, the figures sensible, and a re-run skips every finished stage."""
    import base64
    import io
    import re

    import numpy as np
    from PIL import Image

    from gf_cli.cmd_demo import STAGES

    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    state = json.loads((out / "demo_state.json").read_text())
    assert list(state["done"]) == list(STAGES)
    page = (out / "report.html").read_text()
    assert "http://" not in page and "https://" not in page  # nothing fetched when opened
    imgs = re.findall(r'src="data:image/(png|gif);base64,([^"]+)"', page)
    assert len(imgs) >= 12, len(imgs)
    for kind, data in imgs:
        im = Image.open(io.BytesIO(base64.b64decode(data)))
        a = np.asarray(im.convert("RGB"), np.float32) / 255
        assert min(im.size) >= 48 and a.std() > 0.02, (kind, im.size, a.std())
    assert Image.open(out / "report" / "preview.gif").n_frames >= 5
    done = state["done"]
    assert done["evaluate"]["test_psnr"] > 20 and done["evaluate"]["gt_to_recon"] < 2.0
    assert done["predict"]["test_psnr"] > 15 and done["edit"]["particles"] < done["reconstruct"]["particles"]
    capsys.readouterr()
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    assert capsys.readouterr().out.count(": done before (") == len(STAGES)


@pytest.fixture(scope="module")
def small_sim(tmp_path_factory):
    from gf_core.formats.hdf5 import write_sim
    from gf_core.synthetic import falling_blob

    p = tmp_path_factory.mktemp("cli") / "sim.h5"
    write_sim(p, falling_blob(n_side=3, frames=3))
    return p


BAD = [
    (["simulate", "hydrostatic_tank", "--fps", "0", "--out", "{tmp}/s.h5"], "--fps: must be a positive number"),
    (["simulate", "water_cube", "--seconds", "-1", "--out", "{tmp}/s.h5"], "--seconds: must be a positive number"),
    (["simulate", "water_cube", "--out", "{tmp}"], "--out names a folder"),
    (["simulate", "water_cube", "--out", "{sim}/x.h5"], "is a file, so it cannot hold"),
    (["simulate", "water_cube", "--device", "foo", "--out", "{tmp}/s.h5"], "unknown device 'foo'"),
    (["render-dataset", "{sim}", "--out", "{tmp}/d", "--frames", "a:b"], "--frames: 'a' is not an integer"),
    (["render-dataset", "{sim}", "--out", "{tmp}/d", "--frames", "1:5:0"], "STEP must be a positive integer"),
    (["render-dataset", "{sim}", "--out", "{tmp}/d", "--fov", "0"], "--fov: must be an angle in (0, 180)"),
    (["render-dataset", "{sim}", "--out", "{tmp}/d", "--frames", "10:20"], "selects none of the simulation's 3 frames"),
    (["bench", "render", "--particles", "abc"], "--particles: 'abc' is not a number"),
    (["bench", "render", "--particles", "-5"], "values must be integers >= 1"),
    (["bench", "render", "--repeats", "0"], "--repeats: must be >= 1"),
    (["bench", "render", "--particles", "1000", "--out", "{sim}/b.json"], "is a file, so it cannot hold"),
    (["bench", "sim", "--solvers", "sph"], "unknown solver 'sph'"),
    (["bench", "render", "--particles", "2000000000"], "GiB free"),
    (["demo", "--time-budget", "0", "--out", "{tmp}/d"], "--time-budget: must be a positive number"),
    (["reconstruct", "{tmp}", "--out", "{tmp}/r", "--iterations", "0"], "--iterations: must be >= 1"),
    (["export", "{tmp}", "--format", "ply"], "no such reconstruction"),
    (["export", "{tmp}", "--format", "ply", "--radius-scale", "0"], "--radius-scale: must be > 0"),
    (["evaluate", "{tmp}", "--rest-density", "-1"], "--rest-density: must be > 0"),
    (["addon", "build", "--platforms", "amiga"], "unknown platform(s) ['amiga']"),
    (["bench", "decoder", "--particles", "0"], "values must be integers >= 1"),
]
if not __import__("torch").cuda.is_available():
    BAD.append((["simulate", "water_cube", "--device", "cuda", "--out", "{tmp}/s.h5"],
                "cuda was asked for but torch sees no CUDA GPU"))


@pytest.mark.parametrize("argv, message", BAD, ids=[" ".join(a[:2]) + " " + m[:18] for a, m in BAD])
def test_user_mistakes_give_one_line_naming_the_option(argv, message, tmp_path, small_sim, capsys):
    """Each of these once ended in a traceback (or after the expensive work); now one line, exit 2."""
    argv = [a.format(tmp=tmp_path, sim=small_sim) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
