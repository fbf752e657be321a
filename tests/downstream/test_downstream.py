"""Downstream tasks (paper Secs. 4.2-4.3): temporal resampling, prediction, editing, their
evaluation, and error against run time for the whole method."""

import json

import numpy as np
import pytest
import torch

from gf_cli.main import main
from gf_core.data import load_dataset
from gf_core.eval.evaluate import evaluate, evaluate_continuation
from gf_core.formats.hdf5 import SimData, read_recon, read_sim, write_sim
from gf_core.eval.metrics import mechanical_energy, particle_error
from gf_core.recon.model import FluidModel
from gf_core.downstream.edit import remove_fraction
from gf_core.downstream.predict import State, continue_state, keep_rest_state, state_at
from gf_core.recon.config import make_config
from gf_core.recon.trainer import reconstruct
from gf_core.sim import simulate
from gf_core.synthetic import falling_blob, splat_dataset


def quiet(*a, **k):
    pass


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    """~250 particles falling and spreading, 5 + 1 views, 8 frames at 10 fps, 64x64."""
    return splat_dataset(tmp_path_factory.mktemp("blob"), falling_blob(n_side=9, frames=8))


@pytest.fixture(scope="module")
def half_rate_run(blob, tmp_path_factory):
    """A reconstruction trained on every other frame (times 0, 0.2, 0.4, 0.6 s)."""
    run = tmp_path_factory.mktemp("half") / "run"
    cfg = make_config("water", overrides={
        "phases": {"iterations": 900, "limit_factor": 1.0}, "model": {"init_particles": 500, "max_particles": 1000},
        "decoder": {"hidden_width": 128, "hidden_layers": 3}, "train": {"eval_every": 300, "checkpoint_every": 900}})
    reconstruct(load_dataset(blob).select_times(slice(None, None, 2)), run, cfg, log=quiet)
    return run


def test_reconstruct_frames_option_trains_on_the_selected_times(blob, tmp_path):
    run = tmp_path / "run"
    assert main(["reconstruct", str(blob), "--out", str(run), "--frames", "1:7:3", "--iterations", "30",
                 "--init-particles", "200", "--quiet"]) == 0
    assert read_recon(run / "recon.h5").config["frame_times_s"] == pytest.approx([0.1, 0.4])
    assert main(["reconstruct", str(blob), "--out", str(tmp_path / "r2"), "--frames", "20:", "--quiet"]) == 2
    assert main(["reconstruct", str(blob), "--out", str(tmp_path / "r3"), "--frames", "::0", "--quiet"]) == 2


def test_upsampled_decoder_is_smoother_than_frame_repetition(blob, half_rate_run, tmp_path):
    """Table 7: at 2x the training rate, the decoder's frames jitter less than repeated frames,
    and on the frames held out in time (0.1, 0.3, 0.5 s) it beats repeating the previous frame."""
    out = tmp_path / "ev"
    r = evaluate(half_rate_run, dataset=load_dataset(blob), upsample=2, out=out, log=quiet)
    u = r["upsample"]
    assert u["heldout_times"] == pytest.approx([0.1, 0.3, 0.5]) and u["heldout_images"] == 15
    assert u["fps"] == pytest.approx(10.0) and u["frames"] == 7
    assert u["jitter"]["decoder"] < u["jitter"]["repetition"], u["jitter"]
    assert u["jitter"]["truth"] < u["jitter"]["repetition"]
    h = u["heldout"]
    assert h["decoder"]["psnr"] > h["repetition"]["psnr"], h
    assert len(list((out / "upsample_x2" / "view_00").glob("*.png"))) == 7
    assert (out / "eval_upsample.png").stat().st_size > 5000


def test_continuation_rendered_with_the_learned_appearance_matches_the_reconstruction(blob, half_rate_run, tmp_path):
    """A sim.h5 starting at 0.6 s whose particles are the decoder's own renders as the
    reconstruction does at 0.6 s: the appearance (scale, rotation, opacity, colour of each source
    Gaussian at the start time) is carried right, particle by particle (the order is shuffled)."""
    r = read_recon(half_rate_run / "recon.h5")
    model = FluidModel.from_recon(r)
    with torch.no_grad():
        p = model.at(0.6)["means"].numpy()
    perm = np.random.default_rng(0).permutation(len(p))
    pos = np.stack([p[perm], p[perm]])
    write_sim(tmp_path / "same.h5", SimData(positions=pos, velocities=np.zeros_like(pos), fps=1000.0,
                                            particle_radius=0.025, times=np.array([0.599, 0.6]), source_index=perm,
                                            config={"recon": str(half_rate_run / "recon.h5"), "start_time_s": 0.6}))
    ds = load_dataset(blob).with_times([0.6])
    ev = evaluate_continuation(tmp_path / "same.h5", dataset=ds, log=quiet)
    ref = evaluate(half_rate_run, dataset=ds, out=tmp_path / "ref", log=quiet)
    assert ev["train"]["per_frame"][0]["psnr"] == pytest.approx(ref["train"]["per_frame"][0]["psnr"], abs=1e-3)
    assert ev["train"]["psnr_mean"] > 30
    assert (tmp_path / "same_eval.png").exists() and "particles_vs_gt" in ev


def test_predict_and_edit_from_a_reconstruction(blob, half_rate_run, tmp_path, capsys):
    assert main(["predict", str(half_rate_run), "--frames", "1", "--fps", "10", "--out", str(tmp_path / "p.h5"),
                 "--quiet"]) == 0
    p = read_sim(tmp_path / "p.h5")
    n = read_recon(half_rate_run / "recon.h5").num_particles
    assert p.complete and p.num_particles == n and p.times == pytest.approx([0.6, 0.7])
    assert np.array_equal(p.source_index, np.arange(n))
    assert main(["evaluate", str(tmp_path / "p.h5")]) == 0
    ev = json.loads((tmp_path / "p_eval.json").read_text())
    assert ev["train"]["per_frame"][0]["time"] == pytest.approx(0.7) and ev["train"]["psnr_mean"] > 15
    assert ev["particles_vs_gt"]["per_frame"][-1]["gt_frame"] == 7
    # editing (Fig. 10): half the particles removed -> half the mass; the rest stays in the box
    assert main(["edit", str(half_rate_run), "--at", "0.2", "--remove-fraction", "0.5", "--frames", "6", "--fps",
                 "10", "--out", str(tmp_path / "e.h5"), "--quiet"]) == 0
    e = read_sim(tmp_path / "e.h5")
    assert e.num_particles == n - round(0.5 * n) and len(set(e.source_index.tolist())) == e.num_particles
    pm = read_sim(tmp_path / "p.h5").config
    em = e.config
    state = state_at(read_recon(half_rate_run / "recon.h5"), 0.2)
    full = keep_rest_state(state, "pbf")
    assert em["particle_mass"] == pytest.approx(full.rest[2] * 1000.0)
    assert em["particle_mass"] * e.num_particles == pytest.approx(0.5 * full.rest[2] * 1000.0 * n, rel=0.01)
    assert pm["spacing"] > 0
    lo, hi = np.asarray(e.domain_min), np.asarray(e.domain_max)
    assert np.all(e.positions >= lo - 1e-6) and np.all(e.positions <= hi + 1e-6)
    assert main(["edit", str(half_rate_run), "--out", str(tmp_path / "x.h5")]) == 2
    assert "no edit given" in capsys.readouterr().err
    assert main(["edit", str(half_rate_run), "--remove-box", "0", "0", "0", "-1", "1", "1", "--out",
                 str(tmp_path / "x.h5")]) == 2
    assert main(["predict", str(half_rate_run), "--at", "5", "--out", str(tmp_path / "x.h5")]) == 2
    assert "outside the reconstructed clip" in capsys.readouterr().err
    assert main(["edit", str(half_rate_run), "--add-box", "-0.1", "-0.1", "0.6", "0.1", "0.1", "0.7", "--frames", "1",
                 "--fps", "10", "--out", str(tmp_path / "a.h5"), "--quiet"]) == 0
    a = read_sim(tmp_path / "a.h5")
    assert a.num_particles > n and a.source_index.max() < n


def test_prediction_from_the_true_state_beats_a_perturbed_one_and_energy_falls_at_impact():
    """Table 8's premise: the better the starting particles, the better the prediction. A water
    sphere (DFSPH ground truth) is continued from frame 1 through its impact on the floor."""
    gt, _ = simulate("water_sphere", particles=500, fps=30, seconds=0.4)
    sp = 2 * gt.particle_radius
    dom = (np.asarray(gt.domain_min), np.asarray(gt.domain_max))
    rng = np.random.default_rng(0)
    x, v = gt.positions[1], gt.velocities[1]
    noisy = State(x + rng.normal(scale=0.5 * sp, size=x.shape), v + rng.normal(scale=0.3, size=v.shape),
                  np.arange(len(x)), gt.times[1], dom)
    errs, energy = {}, None
    for name, s in (("true", State(x, v, np.arange(len(x)), gt.times[1], dom)), ("perturbed", noisy)):
        sim, rep = continue_state(s, frames=6, fps=30, solver="dfsph")
        errs[name] = particle_error(sim.positions[-1], gt.positions[7], sp)["chamfer"]
        if name == "true":
            assert sim.times == pytest.approx(gt.times[1:8])
            long, rep = continue_state(s, frames=10, fps=30, solver="dfsph")
            energy = [mechanical_energy(long.positions[k], long.velocities[k], rep["particle_mass"], 0.0)["total"]
                      for k in range(long.num_frames)]
    assert errs["true"] < 0.3 and errs["perturbed"] > 2 * errs["true"], errs
    # free fall keeps the mechanical energy; the impact (t ~ 0.24 s) dissipates much of it
    assert abs(energy[5] - energy[0]) < 0.02 * energy[0]
    assert energy[-1] < 0.8 * energy[0], energy


def test_remove_fraction_halves_the_particles():
    s = State(np.random.default_rng(0).random((1000, 3)), np.zeros((1000, 3)), np.arange(1000), 0.0,
              (np.zeros(3), np.ones(3)))
    h = remove_fraction(s, 0.5)
    assert len(h) == 500 and len(np.unique(h.source_index)) == 500 and h.edits[0]["removed"] == 500
    with pytest.raises(Exception, match="remove-fraction"):
        remove_fraction(s, 1.0)


def test_bench_prediction_error_against_cost(tmp_path):
    from gf_core.bench.sim_bench import bench_prediction, plot_prediction

    recs = bench_prediction(["dfsph", "pbf"], 300, start_frame=1, frames=3, log=quiet)
    assert len(recs) == 6 and all(r["wall_s"] > 0 and np.isfinite(r["chamfer_final"]) for r in recs)
    strict = [r for r in recs if r["solver"] == "dfsph"][-1]  # the reference's own settings
    assert strict["chamfer_final"] < 0.2, strict
    plot_prediction(recs, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 10000


def test_bench_reconstruct_sweeps_budgets_and_plots(blob, tmp_path):
    out = tmp_path / "bench"
    assert main(["bench", "reconstruct", str(blob), "--iterations", "40,120", "--particles", "150,300",
                 "--out", str(out)]) == 0
    recs = json.loads((out / "bench_reconstruct.json").read_text())["records"]
    assert sorted((r["iterations_budget"], r["particle_budget"]) for r in recs) == \
        [(40, 150), (40, 300), (120, 150), (120, 300)]
    assert all(r["particles"] <= r["particle_budget"] and r["iterations"] <= r["iterations_budget"] for r in recs)
    assert all(np.isfinite(r["test_psnr"]) and np.isfinite(r["chamfer"]) and r["wall_s"] > 0 for r in recs)
    # more iterations at the same particle budget: a better training fit
    for n in (150, 300):
        a, b = (next(r for r in recs if r["particle_budget"] == n and r["iterations_budget"] == it) for it in (40, 120))
        assert b["train_psnr"] > a["train_psnr"]
    assert (out / "error_vs_time.png").stat().st_size > 20000
    assert main(["bench", "reconstruct", str(blob), "--iterations", "0", "--out", str(out)]) == 2


def test_bench_reconstruct_per_frame_fits_each_frame_alone(blob, tmp_path):
    out = tmp_path / "pf"
    assert main(["bench", "reconstruct", str(blob), "--per-frame", "--frames", "0:8:7", "--iterations", "60",
                 "--particles", "200", "--out", str(out)]) == 0
    doc = json.loads((out / "bench_reconstruct.json").read_text())
    recs = doc["records"]
    assert doc["per_frame"] and [round(r["time"], 4) for r in recs] == sorted(round(r["time"], 4) for r in recs)
    assert len(recs) == 2 and recs[0]["time"] < recs[1]["time"]
    for r in recs:  # a static fit: no decoder in its recon.h5, evaluated on that frame only
        rr = read_recon(out / f"run_it60_n200_t{r['time']:.4f}" / "recon.h5")
        assert rr.decoder is None and np.isfinite(r["test_psnr"]) and np.isfinite(r["chamfer"])
    assert (out / "per_frame.png").stat().st_size > 10000


def test_bench_reconstruct_reads_the_images_as_reconstruct_does(blob, tmp_path):
    """--grayscale and --resolution reach the runs: one channel, the smaller cameras."""
    out = tmp_path / "gray"
    assert main(["bench", "reconstruct", str(blob), "--per-frame", "--frames", "0:1", "--iterations", "10",
                 "--particles", "100", "--grayscale", "--resolution", "16", "--out", str(out)]) == 0
    run = next(out.glob("run_it10_n100_t*"))
    rr = read_recon(run / "recon.h5")
    assert rr.channels == 1 and rr.config["dataset_options"] == {"grayscale": True, "resolution": 16}


def test_pareto_front():
    from gf_core.bench.recon_bench import pareto

    pts = [(1, 20.0), (2, 19.0), (3, 25.0), (4, 24.0), (5, 26.0)]
    assert pareto(pts, True) == [0, 2, 4]
    assert pareto([(1, 2.0), (2, 1.0), (3, 1.5)], False) == [0, 1]
