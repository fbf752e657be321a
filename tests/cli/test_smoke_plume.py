"""The synthetic smoke plume end to end with the project's commands: simulate (a density grid),
render-dataset (ray-marched, grayscale, the grid beside it), reconstruct (smoke preset) and
evaluate (the reconstruction's density against the true grid)."""

import json
import math

import numpy as np

from gf_cli.main import main
from gf_core.data import load_dataset
from gf_core.formats.hdf5 import read_grid


def test_plume_simulate_render_reconstruct_evaluate(tmp_path):
    plume, ds, run = tmp_path / "plume.h5", tmp_path / "ds", tmp_path / "run"
    assert main(["simulate", "smoke_plume", "--out", str(plume), "--cells", "16", "--seconds", "0.6",
                 "--fps", "10"]) == 0
    g = read_grid(plume)
    assert g.density.shape[0] == 7 and g.density[-1].sum() > 0
    assert main(["render-dataset", str(plume), "--out", str(ds), "--views", "3", "--test-views", "1",
                 "--resolution", "24", "--frames", "2:7:2"]) == 0
    train = load_dataset(ds, grayscale=True)
    assert train.views == [0, 1, 2] and np.allclose(train.times, [0.2, 0.4, 0.6])
    assert train.meta["gt_density"].endswith("gt_density.h5")
    assert np.allclose(train.meta["scene_box"], [g.domain_min, g.domain_max])
    img = train.load(train.indices(time=0.6)[0])[0]
    assert img.shape == (24, 24, 1) and img.max() > 0.1 and img.min() == 0.0
    cfg = tmp_path / "tiny.toml"
    cfg.write_text("[model]\ninit_particles = 200\nmax_particles = 400\n[decoder]\nhidden_width = 16\n"
                   "hidden_layers = 1\nfeature_dim = 4\n[train]\neval_every = 40\ncheckpoint_every = 40\n")
    assert main(["reconstruct", str(ds), "--out", str(run), "--preset", "smoke", "--config", str(cfg),
                 "--grayscale", "--iterations", "40", "--quiet"]) == 0
    assert main(["evaluate", str(run)]) == 0
    dv = json.loads((run / "eval.json").read_text())["density_vs_gt"]
    assert [round(r["time"], 3) for r in dv["per_frame"]] == [0.2, 0.4, 0.6]
    assert all(math.isfinite(r["corr"]) and -1 <= r["corr"] <= 1 and r["error"] >= 0 for r in dv["per_frame"])
    assert math.isfinite(dv["corr_mean"]) and math.isfinite(dv["error_mean"])
    assert dv["grid"] == list(g.density.shape[1:])
    # the per-frame reference on the same dataset (static fits: their parameters carry gradients)
    bench = tmp_path / "per_frame"
    assert main(["bench", "reconstruct", str(ds), "--per-frame", "--frames", "1:3", "--preset", "smoke",
                 "--config", str(cfg), "--grayscale", "--iterations", "20", "--particles", "200",
                 "--out", str(bench)]) == 0
    rows = json.loads((bench / "bench_reconstruct.json").read_text())["records"]
    assert [round(r["time"], 3) for r in rows] == [0.4, 0.6]
    assert all(-1 <= r["density_corr"] <= 1 and r["density_corr_min_frame"] == r["density_corr"] for r in rows)
