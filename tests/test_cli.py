"""The gf-cli entry point: every command has --help; the demo runs end to end on tiny settings."""

import importlib.util
import json
import subprocess
import sys

import pytest

from gf_cli.main import COMMANDS, build_parser, main

EXPECTED = {"demo", "simulate", "render-dataset", "inspect", "bench"}


def test_help_lists_commands_and_each_has_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert all(c in out for c in EXPECTED)
    for cmd in EXPECTED | {"bench render", "bench sim"}:
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


@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="bpy not installed")
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--particles", "400", "--seconds", "0.2", "--resolution", "48",
                 "--samples", "4"]) == 0
    report = json.loads((out / "demo_report.json").read_text())
    assert report["simulate"]["particles"] > 300
    assert report["splat_vs_blender_alpha_iou"]["mean"] > 0.5
    assert (out / "contact_sheet.png").stat().st_size > 1000
    assert (out / "dataset" / "transforms_train.json").exists()
