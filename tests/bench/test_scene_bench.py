"""The scene matrix's machinery (``gf-cli bench scenes --quick``)."""

import json

import numpy as np
import pytest

from gf_cli.main import main as gf_cli


# ---- the scene matrix ----------------------------------------------------------------------------------
@pytest.mark.blender
def test_bench_scenes_quick_makes_every_scene_kind_and_judges_it(tmp_path, monkeypatch):
    """gf-cli bench scenes --quick: every scene of the suite simulated, rendered (with its rig, look
    and layout), reconstructed, evaluated and set beside its per-frame fit, with finite, sensible
    figures; a re-run finds every step complete and runs none."""
    from gf_core.bench.scene_bench import load_suite

    out = tmp_path / "m"
    assert gf_cli(["bench", "scenes", "--quick", "--out", str(out)]) == 0
    suite = load_suite(quick=True)
    res = json.loads((out / "bench_scenes.json").read_text())
    recs = {r["scene"]: r for r in res["records"]}
    assert set(recs) == set(suite["scenes"]) and len(recs) >= 7
    for name, r in recs.items():
        assert 8 < r["test_psnr_mean"] < 60 and r["test_psnr_min"] <= r["test_psnr_mean"], name
        assert 0 < r["test_ssim"] <= 1 and 8 < r["per_frame_test_psnr_mean"] < 60, name
        assert 0 <= r["gt_to_recon_mean"] <= r["gt_to_recon_max"] < 50, name
        assert 0 <= r["recon_to_gt_mean"] <= r["recon_to_gt_max"] < 50, name
        assert 0 <= r["outside_max"] <= 1 and 0 < r["coverage"] <= 1, name
        assert np.isfinite(r["kinetic_factor_max"]) and r["kinetic_factor_max"] >= 1, name
        # the kinetic factor splits into the mass estimate's and the speeds' (per kilogram)
        assert r["specific_kinetic_factor_max"] >= 1 and r["mass_ratio"] > 0, name
        mass_factor = max(r["mass_ratio"], 1 / r["mass_ratio"])
        assert r["kinetic_factor_max"] <= r["specific_kinetic_factor_max"] * mass_factor * (1 + 1e-9), name
        assert r["wall_s"] >= 0.95 * suite["scenes"][name]["time_budget"], name
        assert set(r["targets"]) >= {"test_psnr_mean", "chamfer_max", "outside_max", "kinetic_factor",
                                     "not_below_per_frame"}, name
        assert (out / f"scene_{name}.png").exists()
    # each scene's own set-up reached its dataset
    tr = lambda name: json.loads((out / name / "dataset" / "transforms_train.json").read_text())  # noqa: E731
    te = lambda name: json.loads((out / name / "dataset" / "transforms_test.json").read_text())  # noqa: E731
    assert "scene_box" not in tr("no_box") and all("time_s" in f for f in tr("no_box")["frames"])
    assert "scene_box" in tr("water_sphere")
    elev = lambda m: np.degrees(np.arcsin((np.asarray(m)[2, 3] - 0.4) / np.linalg.norm(np.asarray(m)[:3, 3] - [0, 0, 0.4])))  # noqa: E731
    assert elev(te("rig_arc120")["frames"][0]["transform_matrix"]) == pytest.approx(35.0, abs=0.5)
    assert elev(tr("rig_arc120")["frames"][0]["transform_matrix"]) == pytest.approx(20.0, abs=0.5)
    assert len({f["view_id"] for f in tr("tiny_3view")["frames"]}) == 3
    manifest = json.loads((out / "splash" / "dataset" / "manifest.json").read_text())
    assert manifest["options"]["transmission"] == pytest.approx(0.9) and manifest["options"]["blob"] == 2.0
    # a re-run: every step complete, no command run
    from gf_core.batch import runner

    ran = []
    monkeypatch.setattr(runner, "attempt", lambda job, *a: ran.append(job.name))
    assert gf_cli(["bench", "scenes", "--quick", "--out", str(out), "--only", "splash,no_box"]) == 0
    assert ran == []
