"""Dataset time and views as users' files have them: normalised time, D-NeRF's time_s, view ids,
background names."""

import json
import shutil

import numpy as np
import pytest

from gf_core.data import load_dataset
from gf_core.errors import InputError


# ---- datasets as users have them ---------------------------------------------------------------------
def test_normalized_time_becomes_seconds_and_view_ids_do_not_collide(blob, tmp_path):
    import shutil

    root = tmp_path / "dnerf"
    shutil.copytree(blob, root)
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        times = sorted({f["time"] for f in meta["frames"]})
        for f in meta["frames"]:
            f["time"] = f["time"] / times[-1]           # D-NeRF: clip fraction in [0, 1]
            f["camera_id"] = f.pop("view_id") % 5        # test camera numbered from 0 in its own file
        meta["time_unit"] = "normalized"
        meta.pop("fps", None)
        p.write_text(json.dumps(meta))
    ds = load_dataset(root, duration=0.7)
    assert ds.meta["time_source"].startswith("normalized x duration")
    assert max(f.time for f in ds.frames) == pytest.approx(0.7)
    ds = load_dataset(root, fps=10.0)
    assert max(f.time for f in ds.frames) == pytest.approx(0.7)
    test = load_dataset(root, split="test", fps=10.0)
    assert set(test.views).isdisjoint(set(ds.views))     # the held-out camera keeps its own id
    raw = load_dataset(root)
    assert "no fps or duration" in raw.meta["time_source"]
    with pytest.raises(InputError, match="--fps must be a positive number"):
        load_dataset(root, fps=-1.0)


def test_bad_view_id_and_background_name_the_file(blob, tmp_path):
    import shutil

    root = tmp_path / "bad"
    shutil.copytree(blob, root)
    p = root / "transforms_train.json"
    meta = json.loads(p.read_text())
    meta["frames"][0]["view_id"] = "left"
    p.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="'view_id' must be an integer, got 'left'"):
        load_dataset(root)
    meta["frames"][0]["view_id"] = 0
    meta["background"] = "black"
    p.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="'background' must be a colour: a number or 3 numbers in \\[0, 1\\], got 'black'"):
        load_dataset(root)


# ---- D-NeRF time with time_s ------------------------------------------------------------------------
def test_the_loader_reads_time_s_beside_a_normalised_time(small_blob, tmp_path):
    root = tmp_path / "dnerf"
    shutil.copytree(small_blob, root)
    seconds = {}
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        times = sorted({f["time"] for f in meta["frames"]})
        seconds[split] = times
        for f in meta["frames"]:
            f["time_s"] = f["time"]
            f["time"] = (f["time"] - times[0]) / (times[-1] - times[0])
        meta.pop("fps", None)
        meta.pop("time_unit", None)
        p.write_text(json.dumps(meta))
    for fps in (None, 30.0):  # a given --fps does not override seconds the frames carry
        ds = load_dataset(root, fps=fps)
        assert np.allclose(ds.times, seconds["train"])
        assert ds.meta["time_source"].startswith("time_s")
    assert np.allclose(load_dataset(root, split="test").times, seconds["test"])
    p = root / "transforms_train.json"
    meta = json.loads(p.read_text())
    del meta["frames"][1]["time_s"]
    p.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="carry 'time_s'"):
        load_dataset(root)
