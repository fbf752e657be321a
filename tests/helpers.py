"""Small helpers shared by the tests (the root conftest puts this folder on the import path)."""

import numpy as np

from gf_core.recon.config import make_config


def without_scene_box(src, dst):
    """A copy of the NeRF-layout dataset ``src`` at ``dst`` whose transforms files carry no scene box,
    as real footage comes; returns (dst, the box that was removed)."""
    import json
    import shutil
    from pathlib import Path

    dst = Path(dst)
    shutil.copytree(src, dst)
    for split in ("train", "test"):
        p = dst / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        box = meta.pop("scene_box")
        p.write_text(json.dumps(meta))
    return dst, box


def quiet(*a, **k):
    pass


def _config(base: dict, over: dict):
    for sec, vals in over.items():
        base.setdefault(sec, {}).update(vals)
    return make_config("water", overrides=base)


def small_config(**over):
    """The water preset on a small scene: 900 iterations, 500-1000 particles, a smaller decoder."""
    return _config({"phases": {"iterations": 900, "limit_factor": 1.0},
                    "model": {"init_particles": 500, "max_particles": 1000},
                    "decoder": {"hidden_width": 128, "hidden_layers": 3},
                    "train": {"eval_every": 300, "checkpoint_every": 300}}, over)


def quick_config(**over):
    """Smaller still, for tests of the machinery: 300 iterations, 300-600 particles."""
    return _config({"phases": {"iterations": 300, "limit_factor": 1.0},
                    "model": {"init_particles": 300, "max_particles": 600},
                    "decoder": {"hidden_width": 64, "hidden_layers": 2},
                    "train": {"eval_every": 100, "checkpoint_every": 1000}}, over)


def assert_same_render(a: np.ndarray, b: np.ndarray, what="") -> None:
    """Same seed, same pixels -- up to what a multi-threaded build of Blender's scene (BVH, fluid
    surface) can change from one process to the next: a few pixels come back a level or so apart,
    and up to 0.5 % of them (rays that graze another triangle at the fluid's edge) by more; a
    different seed changes the noise everywhere."""
    assert a.shape == b.shape, what
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
    pix = diff.max(-1) if diff.ndim == 3 else diff
    assert float((pix > 0).mean()) < 0.02 and float((pix > 3).mean()) < 0.005, \
        (what, int(diff.max()), float((pix > 0).mean()), float((pix > 3).mean()))
