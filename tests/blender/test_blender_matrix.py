"""The Blender extension on every Blender it supports: the oldest (4.5 LTS), the default (5.0) and
the newest the bpy module is published for (Python 3.13). Marked ``blender_matrix`` (not in the
default suite: each Blender is a ~350 MB download, installed once into a cached venv under
``~/.cache/gaussfluids/bpy/`` or ``$GF_BPY_CACHE``): ``pytest -m blender_matrix``.

Each Blender installs the zip, imports a reconstruction, evaluates frames and sub-frames against
the torch decoder, renders two looks, bakes USD and OpenVDB, and reads the USD back.
"""

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from test_blender_addon import CAM, FPS, addon_zip, drive, recon_file, sim_file, torch_positions  # noqa: F401

# bpy version -> the CPython it is built for (PyPI: 4.2 - 5.0 are cp311, 5.1 on cp313)
BLENDERS = {"4.5.15": "3.11", "5.0.1": "3.11", "5.3.0": "3.13"}
pytestmark = pytest.mark.blender_matrix


def _interpreter(version: str) -> Path:
    """A python for CPython ``version``: the running one if it matches, else pyenv's."""
    import shutil
    import sys

    if f"{sys.version_info.major}.{sys.version_info.minor}" == version:
        return Path(sys.executable)
    for cand in [shutil.which(f"python{version}")] + sorted(Path.home().glob(f".pyenv/versions/{version}*/bin/python")):
        if cand and subprocess.run([str(cand), "-c", "import sys"], capture_output=True).returncode == 0:
            return Path(cand)
    pytest.fail(f"no Python {version} on this machine for the bpy module that needs it")


def bpy_python(bpy_version: str) -> Path:
    """The interpreter of a cached venv with ``bpy==bpy_version`` from PyPI, made on first use (the
    running one where it has that bpy already)."""
    import importlib.metadata
    import sys

    try:
        if importlib.metadata.version("bpy") == bpy_version:
            return Path(sys.executable)
    except importlib.metadata.PackageNotFoundError:
        pass
    root = Path(os.environ.get("GF_BPY_CACHE", Path.home() / ".cache" / "gaussfluids" / "bpy")) / bpy_version
    py = root / "bin" / "python"
    if py.exists() and subprocess.run([str(py), "-c", "import bpy"], capture_output=True).returncode == 0:
        return py
    subprocess.run([str(_interpreter(BLENDERS[bpy_version])), "-m", "venv", "--clear", str(root)], check=True)
    r = subprocess.run([str(py), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                        f"bpy=={bpy_version}"], capture_output=True, text=True)
    assert r.returncode == 0, f"pip install bpy=={bpy_version}: {r.stderr[-2000:]}"
    return py


@pytest.mark.parametrize("version", list(BLENDERS))
def test_the_extension_works_on_every_supported_blender(version, addon_zip, recon_file, tmp_path):
    py = bpy_python(version)
    out = tmp_path / "out"
    steps = [{"do": "import", "fps": FPS, "frame_end": 10},
             {"do": "frames", "frames": [1, 3.5, 7.25]},
             {"do": "render", "preset": "water", "frames": [1, 9], "camera": CAM, "res": 32, "samples": 4},
             {"do": "render", "preset": "glow", "frames": [1], "camera": CAM, "res": 32, "samples": 4},
             {"do": "bake_vdb"},
             {"do": "bake_usd", "substeps": 2, "replace": False}]
    res, log = drive(addon_zip, recon_file, out, steps, tmp_path / "home", python=py)
    assert res["blender_version"].startswith(version.rsplit(".", 1)[0]), res["blender_version"]
    assert res["import"] == ["FINISHED"] and res["type"] == "POINTCLOUD"
    got = np.load(out / "frames.npz")
    for f in (1, 3.5, 7.25):
        p, _, _ = torch_positions(recon_file, (f - 1) / FPS)
        np.testing.assert_allclose(got[f"p_{f}"], p, atol=1e-5, err_msg=f"Blender {version}, frame {f}")
    assert res["bake_usd"] == ["FINISHED"] and res["bake_vdb"] == ["FINISHED"]
    d = np.load(out / "usd.npz")
    for f in res["usd_frames"]:
        np.testing.assert_array_equal(d[f"usd_{f}"], d[f"live_{f}"])
    assert res["vdb_active"] > 1000
