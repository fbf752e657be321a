"""What a reconstruction needs on scenes it was not tuned on: smooth motion across the training
frames, the scene box or floor a user has, the whole time budget, D-NeRF time in seconds, and the
scene matrix's machinery (``gf-cli bench scenes --quick``)."""

import json
import shutil

import numpy as np
import pytest
import torch

from gf_cli.main import main as gf_cli
from gf_core.data import load_dataset
from gf_core.decoder_np import NumpyDecoder, hermite_coefficients
from gf_core.errors import InputError
from gf_core.io import read_recon
from gf_core.recon_config import make_config
from gf_core.reconstruct import Trainer, reconstruct
from gf_core.synthetic import falling_blob, splat_dataset
from gf_core.temporal import Decoder, DecoderConfig


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    root = tmp_path_factory.mktemp("blob")
    return splat_dataset(root, falling_blob(n_side=7, frames=6))


def quiet(*a, **k):
    pass


def small_config(**over):
    base = {"phases": {"iterations": 300, "limit_factor": 1.0}, "model": {"init_particles": 300, "max_particles": 600},
            "decoder": {"hidden_width": 64, "hidden_layers": 2}, "train": {"eval_every": 100, "checkpoint_every": 1000}}
    for sec, vals in over.items():
        base.setdefault(sec, {}).update(vals)
    return make_config("water", overrides=base)


def residual_decoder(knots, interpolation="hermite", seed=0):
    torch.manual_seed(seed)
    dec = Decoder(40, DecoderConfig(residuals=True, color_residuals=True, residual_interpolation=interpolation,
                                    hidden_width=32, hidden_layers=2), knots=knots)
    with torch.no_grad():
        for p in dec.residuals().values():
            p.normal_(0, 0.05)
        dec.layers[-1].weight.normal_(0, 0.05)
    return dec


# ---- physically smooth motion ---------------------------------------------------------------------
def test_left_and_right_velocities_agree_at_every_training_frame():
    """Hermite residuals: positions and velocities continuous across every knot (a training frame),
    in the torch decoder and in the numpy one the Blender extension and the exports use; the linear
    residuals of older files jump there, which is what the Hermite ones fix."""
    knots = np.sort(np.r_[0.0, np.random.default_rng(3).uniform(0.05, 0.95, 6), 1.0])
    eps = 1e-4
    for interp in ("hermite", "linear"):
        dec = residual_decoder(knots, interp)
        nd = NumpyDecoder(dec.to_data())
        jumps, scale = [], []
        for k in knots[1:-1]:
            with torch.no_grad():
                left, right = dec.forward(k - eps, with_velocity=True), dec.forward(k + eps, with_velocity=True)
            jumps.append(float((left["vp"] - right["vp"]).abs().max()))
            scale.append(max(float(left["vp"].abs().max()), float(right["vp"].abs().max())))
            nl, nr = nd(k - eps, with_velocity=True), nd(k + eps, with_velocity=True)
            assert np.abs(nl["vp"] - left["vp"].numpy()).max() < 1e-3 * max(scale[-1], 1)
            assert np.abs(nr["vp"] - right["vp"].numpy()).max() < 1e-3 * max(scale[-1], 1)
            # positions continuous either way: no step beyond what the speed covers in 2 eps
            assert float((left["dp"] - right["dp"]).abs().max()) <= 1.5 * 2 * eps * scale[-1] + 1e-6
        if interp == "hermite":
            assert max(jumps) < 0.02 * max(scale), (jumps, scale)
        else:
            assert max(jumps) > 0.1 * max(scale)


def test_decoder_joined_at_the_knots_equals_it_there_and_is_smooth_between():
    """time_interpolation = "knots": at a training frame the decoder's output is exactly Phi's there
    (training is unchanged); between frames Phi's knot outputs are joined like the residuals, so
    the velocity is continuous across every frame, matches finite differences, and the numpy
    decoder agrees; a coordinate held at a wall has velocity 0 in both."""
    knots = np.linspace(0, 1, 9)
    dec = residual_decoder(knots)
    dec.cfg.time_interpolation = "knots"
    plain = residual_decoder(knots)  # the same weights, Phi evaluated at tau
    plain.load_state_dict(dec.state_dict())
    nd = NumpyDecoder(dec.to_data())
    assert nd.time_interpolation == "knots"
    with torch.no_grad():
        for k in knots:
            assert torch.allclose(dec.forward(float(k))["dp"], plain.forward(float(k))["dp"], atol=1e-6)
        for tau in (0.07, 0.5 + 1e-3, 0.93):
            a, b = dec.forward(tau, with_velocity=True), nd(tau, with_velocity=True)
            assert np.abs(a["dp"].numpy() - b["dp"]).max() < 1e-5 and np.abs(a["vp"].numpy() - b["vp"]).max() < 1e-4
            h = 1e-4
            fd = (dec.forward(tau + h)["dp"] - dec.forward(tau - h)["dp"]) / (2 * h)
            assert torch.allclose(fd, a["vp"], atol=2e-2 * float(a["vp"].abs().max()))
        assert not torch.allclose(dec.forward(0.07)["dp"], plain.forward(0.07)["dp"], atol=1e-6)  # it does differ between
        for k in knots[1:-1]:
            left, right = dec.forward(k - 1e-5, with_velocity=True)["vp"], dec.forward(k + 1e-5, with_velocity=True)["vp"]
            assert float((left - right).abs().max()) < 1e-2 * float(left.abs().max())
    with pytest.raises(InputError, match="time_interpolation = 'knots' needs residuals"):
        DecoderConfig(time_interpolation="knots").validate()
    # a coordinate held at a wall does not move
    from gf_core.decoder_np import ParticleAnimation
    from gf_core.model import Bounds, FluidModel
    from gf_core.temporal import TimeMap

    n = dec.num_particles
    model = FluidModel(torch.zeros(n, 3), torch.full((n, 3), -4.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                       torch.zeros(n), torch.full((n, 1, 3), 0.5), bounds=Bounds.for_box([-0.02] * 3, [0.02] * 3, 0.01, 0.0),
                       time_map=TimeMap(0.0, 1.0), decoder=dec)
    with torch.no_grad():
        st = model.at(0.43, with_velocity=True)
    held = (st["means"].abs() >= 0.02 - 1e-7)
    assert held.any() and (~held).any()
    assert float(st["velocities"][held].abs().max()) == 0.0 and float(st["velocities"][~held].abs().max()) > 0
    np_st = ParticleAnimation(model.to_recon()).at(0.43, velocity=True)
    assert np.allclose(np_st["velocities"], st["velocities"].numpy(), atol=1e-4)


def test_hermite_residuals_are_exact_at_the_knots_and_for_free_fall():
    """At a knot the value is that knot's residual alone (a training step there trains the same
    value as before); a quadratic in time (free fall) is reproduced with its exact derivative."""
    knots = np.array([0.0, 0.1, 0.35, 0.4, 0.8, 1.0])
    for j, k in enumerate(knots):
        idx, wv, _ = hermite_coefficients(knots, k)
        w = np.zeros(len(knots))
        np.add.at(w, idx, wv)
        assert np.allclose(w, np.eye(len(knots))[j], atol=1e-12)
    q, dq = (lambda x: 4.9 * x ** 2 - 3 * x + 0.5), (lambda x: 9.8 * x - 3)
    for tau in (0.2, 0.37, 0.61):  # interior segments (the first and last use chords at the clip's ends)
        idx, wv, wd = hermite_coefficients(knots, tau)
        assert np.dot(wv, q(knots[idx])) == pytest.approx(q(tau), abs=1e-12)
        assert np.dot(wd, q(knots[idx])) == pytest.approx(dq(tau), abs=1e-10)
    idx, wv, wd = hermite_coefficients(knots, 1.3)  # outside the clip: constant
    assert np.dot(wv, q(knots[idx])) == pytest.approx(q(1.0)) and np.allclose(wd, 0)


def test_old_files_without_an_interpolation_keep_linear_residuals(tmp_path):
    from gf_core.temporal import Decoder as D

    dec = residual_decoder(np.linspace(0, 1, 5), "linear")
    data = dec.to_data()
    del data.encoding["residual_interpolation"]  # as written before the key existed
    assert D.from_data(data).cfg.residual_interpolation == "linear"
    assert NumpyDecoder(data).interpolation == "linear"
    data.encoding["residual_interpolation"] = "spline"
    with pytest.raises(InputError, match="residual_interpolation 'spline'"):
        NumpyDecoder(data)
    with pytest.raises(InputError, match="residual_interpolation must be one of"):
        DecoderConfig(residual_interpolation="cubic").validate()


def test_acceleration_term_is_the_second_difference_and_reaches_only_the_residuals(blob, tmp_path):
    """losses.acceleration: 0 for motion at constant velocity, g in spacings per frame^2 for free
    fall; in the trainer (loss.smooth) it reaches the neighbouring frames' residuals only."""
    from gf_core import losses as L

    x = torch.randn(50, 3)
    v = torch.randn(50, 3)
    h = 0.1
    assert float(L.acceleration(x - v * h, x, x + v * h, h, h, h, 1.0)) == pytest.approx(0.0, abs=1e-10)
    g = torch.tensor([0.0, 0.0, -9.81])
    p = lambda t: x + v * t + 0.5 * g * t * t  # noqa: E731
    # non-uniform steps still give the exact acceleration of a quadratic
    a = L.acceleration(p(-0.05), p(0.0), p(0.12), 0.05, 0.12, 0.1, 0.02)
    assert float(a) == pytest.approx((9.81 * 0.1 ** 2 / 0.02) ** 2, rel=1e-4)
    cfg = small_config(phases={"iterations": 200, "residuals_from": 3}, loss={"smooth": 0.01})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "s", log=quiet)
    tr.initialise()
    tr.phase = 3
    tr._set_lrs(0.5, 0.5)
    with torch.no_grad():
        tr.model.decoder.residual_dp.normal_(0, 0.01)
    times = tr.train.unique_times
    assert tr._smooth_term(float(times[0])) is None and tr._smooth_term(float(times[-1])) is None
    val = tr._smooth_term(float(times[2]))
    val.backward()
    g = tr.model.decoder.residual_dp.grad.abs().sum((0, 2))
    assert set(torch.nonzero(g).flatten().tolist()) <= {1, 2, 3} and float(g[2]) > 0
    assert tr.model.decoder.features.grad is None  # the frozen decoder gets nothing


def test_residual_change_term_is_zero_for_equal_residuals_and_reaches_only_its_frames(blob, tmp_path):
    """losses.residual_change: 0 when the residuals agree, |delta|^2 / spacing^2 otherwise; in the
    trainer (loss.residual_motion) it reaches the drawn frame's and its neighbours' residuals only,
    and one neighbour at the clip's ends."""
    from gf_core import losses as L

    r = torch.randn(40, 3)
    assert float(L.residual_change(r, torch.stack([r, r], 1), 0.1)) == 0.0
    d = torch.tensor([0.02, 0.0, 0.0])
    assert float(L.residual_change(r, (r + d)[:, None], 0.01)) == pytest.approx(4.0, rel=1e-5)
    cfg = small_config(phases={"iterations": 200, "residuals_from": 3}, loss={"residual_motion": 0.01})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "s", log=quiet)
    tr.initialise()
    tr.phase = 3
    with torch.no_grad():
        tr.model.decoder.residual_dp.normal_(0, 0.01)
    times = tr.train.unique_times
    for j, frames in ((0, {0, 1}), (2, {1, 2, 3}), (len(times) - 1, {len(times) - 2, len(times) - 1})):
        tr.model.decoder.residual_dp.grad = None
        tr._residual_motion_term(float(times[j])).backward()
        g = tr.model.decoder.residual_dp.grad.abs().sum((0, 2))
        assert set(torch.nonzero(g).flatten().tolist()) == frames
    assert tr.model.decoder.features.grad is None


def test_particle_volume_is_the_volume_a_packed_block_fills():
    """metrics.particle_volume: N / the median SPH number density; a jittered lattice block of
    12^3 particles at 1 cm fills 12^3 cm^3 (each particle its cell); several frames average; no
    particles is an error."""
    from gf_core.metrics import particle_volume

    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.01
    x = g + np.random.default_rng(0).normal(0, 0.001, g.shape)
    true = len(g) * 0.01 ** 3
    assert particle_volume([x], 0.025) == pytest.approx(true, rel=0.06)
    assert particle_volume([x, 2 * x], 0.05) == pytest.approx(4.5 * true, rel=0.1)  # 1x and 8x the block
    with pytest.raises(ValueError, match="no particles"):
        particle_volume([np.zeros((0, 3))], 0.025)


# ---- the scene box and the floor a user has ------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["--scene-box", "0,0,0,1,1"], "--scene-box: expected six finite numbers"),
    (["--scene-box", "0,0,0,1,1,x"], "--scene-box: expected six finite numbers"),
    (["--scene-box", "0,0,0,1,1,nan"], "--scene-box: expected six finite numbers"),
    (["--scene-box", "0,0,1,1,1,0.5"], "--scene-box: each maximum must exceed its minimum"),
    (["--floor", "low"], "--floor: expected the floor's height as one finite number"),
    (["--floor", "inf"], "--floor: expected the floor's height as one finite number"),
    (["--floor", "0", "--scene-box", "0,0,0,1,1,1"], "--floor: give --scene-box or --floor, not both"),
])
def test_scene_box_and_floor_options_refuse_bad_values_in_one_line(blob, tmp_path, capsys, argv, message):
    rc = gf_cli(["reconstruct", str(blob), "--out", str(tmp_path / "run"), "--quiet"] + argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "run").exists()  # refused before any work


def test_scene_box_and_floor_reach_the_trainer_and_recon_h5(blob, tmp_path):
    root = tmp_path / "nobox"
    shutil.copytree(blob, root)
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        box = meta.pop("scene_box")
        p.write_text(json.dumps(meta))
    ds = load_dataset(root)
    said = []
    tr = Trainer(small_config(), ds, out=tmp_path / "a", log=said.append)
    tr.initialise()
    assert tr.box_source == "cameras"
    assert any("--scene-box" in s and "--floor" in s and "floor and settle terms are off" in s for s in said)
    tr = Trainer(small_config(model={"floor": [-0.05]}), ds, out=tmp_path / "b", log=quiet)
    tr.initialise()
    assert tr.box_source == "cameras, floor from config" and tr.model.bounds.lo[2] == pytest.approx(-0.05)
    # a floor in the dataset's own file
    p = root / "transforms_train.json"
    meta = json.loads(p.read_text())
    p.write_text(json.dumps({**meta, "floor": -0.04}))
    tr = Trainer(small_config(), load_dataset(root), out=tmp_path / "c", log=quiet)
    tr.initialise()
    assert tr.box_source == "cameras, floor from dataset" and tr.model.bounds.lo[2] == pytest.approx(-0.04)
    p.write_text(json.dumps({**meta, "floor": "ground"}))
    with pytest.raises(InputError, match="'floor' must be a finite number"):
        load_dataset(root)
    p.write_text(json.dumps(meta))
    # the CLI's box lands in recon.h5
    text = ",".join(f"{v:g}" for v in box[0] + box[1])
    rc = gf_cli(["reconstruct", str(root), "--out", str(tmp_path / "run"), "--quiet", "--iterations", "30",
                 "--init-particles", "200", f"--scene-box={text}"])
    assert rc == 0
    r = read_recon(tmp_path / "run" / "recon.h5")
    assert r.config["scene_box_source"] == "config"
    assert np.allclose(r.config["config"]["model"]["scene_box"], box, atol=1e-5)
    assert r.config["bounds"]["lo"] == pytest.approx(box[0], abs=1e-5)
    # the fluid volume (the particles' mass) comes from the trained particles, the hull's beside it
    assert r.config["fluid_volume"] > 0 and r.config["hull_volume"] > 0
    with pytest.raises(InputError, match="model.floor must be"):
        small_config(model={"floor": [0.0, 1.0]})


# ---- the whole budget -------------------------------------------------------------------------------
def test_a_run_with_a_time_budget_uses_it_all_and_says_why_each_phase_ended(blob, tmp_path):
    """With a time budget the iteration caps do not end a phase (here phases.iterations is far too
    small for the seconds): every phase ends at its share of the time, and the run uses >= 95 % of it."""
    budget = 12.0
    said = []
    cfg = small_config(phases={"iterations": 60}, train={"time_budget_s": budget, "eval_every": 10_000})
    m = reconstruct(load_dataset(blob), tmp_path / "run", cfg, log=said.append)
    assert m["wall_s"] >= 0.95 * budget
    assert m["iterations"] > 60
    ends = m["phase_ends"]
    assert [e["phase"] for e in ends] == [1, 2, 3]
    assert all("time budget" in e["reason"] for e in ends)
    assert sum("phase 3 ends" in s and "time budget" in s for s in said) == 1
    assert read_recon(tmp_path / "run" / "recon.h5").metrics["phase_ends"] == ends
    # without a budget the caps end the phases, and the log says so
    m = reconstruct(load_dataset(blob), tmp_path / "run2", small_config(phases={"iterations": 60}), log=quiet)
    assert m["iterations"] == 60 and all("iteration cap" in e["reason"] for e in m["phase_ends"])



def test_without_a_budget_a_phase_still_improving_at_its_cap_goes_on_to_its_plateau(blob, tmp_path):
    """Without a time budget the caps set the schedule, not the end: a phase whose image loss still
    improves at its cap goes on until the plateau test ends it, at most phases.limit_factor x its
    cap. The plateau test watches the loss only once the ramps (and phase 2's widening time window)
    are done, so a plateau comes no earlier than one window after them. Here the window (30
    iterations) is longer than phase 1's cap (12), so phase 1 cannot end at its cap."""
    window, factor = 30, 4.0
    cfg = small_config(phases={"iterations": 60, "limit_factor": factor, "plateau_window": window},
                       train={"eval_every": 10_000})
    said = []
    m = reconstruct(load_dataset(blob), tmp_path / "run", cfg, log=said.append)
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "probe", log=quiet)
    caps = [tr.phase_cap(k) for k in (1, 2, 3)]
    assert caps == [12, 27, 21]
    ends, before = m["phase_ends"], 0
    assert [e["phase"] for e in ends] == [1, 2, 3]
    watched_from = [0.25 * caps[0], max(0.25, cfg.phases.time_curriculum) * caps[1], 0.25 * caps[2]]
    for e, cap, start in zip(ends, caps, watched_from):
        ran, before = e["iteration"] - before, e["iteration"]
        if e["reason"].startswith("plateau"):
            assert ran > start + window, (e, ran)
        else:
            assert ran == round(factor * cap) and "iteration limit" in e["reason"], (e, ran)
    assert ends[0]["iteration"] > caps[0]  # phase 1 ran past its cap
    assert m["iterations"] > 60
    assert sum("phase 1 ends" in s for s in said) == 1


# ---- D-NeRF time with time_s ------------------------------------------------------------------------
def test_the_loader_reads_time_s_beside_a_normalised_time(blob, tmp_path):
    root = tmp_path / "dnerf"
    shutil.copytree(blob, root)
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


# ---- the scene matrix ----------------------------------------------------------------------------------
@pytest.mark.blender
def test_bench_scenes_quick_makes_every_scene_kind_and_judges_it(tmp_path, monkeypatch):
    """gf-cli bench scenes --quick: every scene of the suite simulated, rendered (with its rig, look
    and layout), reconstructed, evaluated and set beside its per-frame fit, with finite, sensible
    figures; a re-run finds every step complete and runs none."""
    from gf_core.bench import scene_bench
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
    monkeypatch.setattr(scene_bench, "_gf", lambda *a, **k: pytest.fail(f"re-ran {a[2]}"))
    assert gf_cli(["bench", "scenes", "--quick", "--out", str(out), "--only", "splash,no_box"]) == 0
