"""The trainer on scenes with known particles: what it reaches, resuming, the model's bounds, the
scene box a user gives, bad input and configs, the command line."""

import json
import math
import shutil

import numpy as np
import pytest
import torch

from gf_cli.main import main as gf_cli
from gf_core.data import load_dataset
from gf_core.errors import InputError
from gf_core.eval.evaluate import evaluate
from gf_core.formats.hdf5 import read_recon
from gf_core.recon.config import ReconConfig, make_config
from gf_core.recon.decoder import DecoderConfig, TimeMap
from gf_core.recon.model import FluidModel
from gf_core.recon.trainer import ReconstructionError, Trainer, reconstruct
from gf_core.synthetic import falling_blob, splat_dataset
from helpers import quick_config, quiet, small_config, without_scene_box


def test_frozen_decoder_leaves_theta_and_phi_as_phase_2_left_them(blob, tmp_path):
    cfg = small_config(phases={"iterations": 200, "freeze_decoder": True}, decoder={"residuals": True})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "run", log=quiet)
    orig, seen = tr.step, {}

    def step(*a):
        if tr.phase == 3 and not seen:
            seen["phi"] = [p.detach().clone() for p in [tr.model.decoder.features, *tr.model.decoder.mlp_parameters()]]
            seen["res"] = tr.model.decoder.residual_dp.detach().clone()
        return orig(*a)

    tr.step = step
    tr.run()
    dec = tr.model.decoder
    assert seen and dec.frozen
    assert all(torch.equal(a, b) for a, b in zip(seen["phi"], [dec.features, *dec.mlp_parameters()]))
    assert not torch.equal(seen["res"], dec.residual_dp)  # the residuals did train in phase 3
    with pytest.raises(InputError, match="freeze_decoder needs decoder.residuals"):
        small_config(phases={"freeze_decoder": True}, decoder={"residuals": False}).validate()


def test_particle_centres_stay_the_wall_inset_inside_the_box_and_old_files_have_none():
    """Bounds.inset (model.wall_inset x spacing): decoded and projected centres are clamped to the
    box shrunk by it on every face (a face pair nearer than twice the inset meets in the middle),
    the numpy decoder clamps the same, it survives recon.h5, and a recon.h5 written before it
    existed (bounds without "inset") clamps to the faces as before."""
    from gf_core.formats.decoder_np import ParticleAnimation
    from gf_core.recon.model import Bounds

    b = Bounds.for_box([-0.4, -0.4, 0.0], [0.4, 0.4, 0.01], 0.02, inset=0.01)
    clo, chi = b.centre_box()
    assert np.allclose(clo, [-0.39, -0.39, 0.005]) and np.allclose(chi, [0.39, 0.39, 0.005])
    assert Bounds.from_dict(b.to_dict()) == b
    old = b.to_dict()
    del old["inset"]
    assert Bounds.from_dict(old).inset == 0.0
    pts = torch.tensor([[0.0, 0.0, -0.3], [0.5, -0.5, 0.004], [0.1, 0.2, 0.9]])
    model = FluidModel.from_points(pts, radius=0.01, color=(0.5, 0.5, 0.5), opacity=0.5, sh_degree=1, channels=3,
                                   bounds=Bounds.for_box([-0.4, -0.4, 0.0], [0.4, 0.4, 0.8], 0.02, inset=0.01),
                                   time_map=TimeMap(0.0, 1.0), decoder_cfg=DecoderConfig())
    want = np.array([[0.0, 0.0, 0.01], [0.39, -0.39, 0.01], [0.1, 0.2, 0.79]])
    with torch.no_grad():
        assert np.allclose(model.at(0.5)["means"].numpy(), want, atol=1e-6)
    rec = model.to_recon(config={"spacing": 0.02})
    assert np.allclose(ParticleAnimation(rec).at(0.5)["positions"], want, atol=1e-6)
    assert FluidModel.from_recon(rec).bounds.inset == 0.01
    del rec.config["bounds"]["inset"]  # as version-1..3 files have them
    with torch.no_grad():
        assert float(FluidModel.from_recon(rec).at(0.5)["means"][0, 2]) == 0.0
    assert float(ParticleAnimation(rec).at(0.5)["positions"][0, 2]) == 0.0
    model.project_()
    assert np.allclose(model.means.detach().numpy(), want, atol=1e-6)
    with pytest.raises(InputError, match="wall_inset"):
        make_config("water", overrides={"model": {"wall_inset": -0.1}})


def test_tiny_scene_reconstruction_meets_psnr_and_chamfer(blob, tmp_path):
    """The reconstruction's first target: training PSNR >= 30 dB, both Chamfer directions < 1 true
    particle spacing at every frame, on CPU in well under 3 minutes."""
    run = tmp_path / "run"
    m = reconstruct(load_dataset(blob), run, small_config(), test_dataset=load_dataset(blob, split="test"), log=quiet)
    assert m["bad_steps"] == 0  # its run time (about 35 s alone on 2 cores) is in BENCHMARKS.md, not asserted
    r = evaluate(run, dataset=load_dataset(blob), test_dataset=load_dataset(blob, split="test"), log=quiet)
    assert r["train"]["psnr_mean"] >= 30.0, r["train"]["psnr_mean"]
    pv = r["particles_vs_gt"]
    assert pv["gt_to_recon_max_frame"] < 1.0 and pv["recon_to_gt_max_frame"] < 1.0, pv
    assert r["test"]["psnr_mean"] > 25.0
    # physics (paper Fig. 5, Table 3): the blob falls, so kinetic energy grows and potential
    # energy drops, in the reconstruction (decoder velocities) as in the ground truth
    en = r["energy"]["per_frame"]
    assert np.mean([x["kinetic"] for x in en[4:]]) > 2 * en[0]["kinetic"]
    assert en[-1]["gt_kinetic"] > 2 * en[0]["gt_kinetic"]
    assert en[-1]["potential"] < en[0]["potential"] and en[-1]["gt_potential"] < en[0]["gt_potential"]
    # the kinetic energy is the estimated mass times half the mean squared speed, in both
    e = r["energy"]
    for x in en:
        assert x["kinetic"] == pytest.approx(0.5 * e["mass_total"] * x["speed_rms"] ** 2, rel=1e-6)
        assert x["gt_kinetic"] == pytest.approx(0.5 * e["gt_mass_total"] * x["gt_speed_rms"] ** 2, rel=1e-6)
    assert pv["emd_mean"] < pv["emd_floor"] + 1.0
    assert r["particle_stats"]["count"] == r["particles"] and 0 < r["particle_stats"]["opacity"]["median"] <= 1
    # the files: metrics.jsonl has the logged fields, recon.h5 reads back with its decoder
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert {1, 2, 3} <= {x["phase"] for x in lines}
    for key in ("wall_s", "iteration", "phase", "terms", "weights", "train_psnr", "particles"):
        assert key in lines[-1]
    assert any("test_psnr" in x for x in lines)
    assert all(b["wall_s"] >= a["wall_s"] for a, b in zip(lines, lines[1:]))
    rec = read_recon(run / "recon.h5")
    assert rec.decoder is not None and rec.decoder.features.shape == (rec.num_particles, 64)
    # model.wall_inset: every decoded centre half a trainer spacing inside the scene box, in torch
    # and in the numpy decoder the Blender extension uses
    from gf_core.formats.decoder_np import ParticleAnimation

    b = rec.config["bounds"]
    assert math.isclose(b["inset"], 0.5 * rec.config["spacing"], rel_tol=1e-6)
    model, anim = FluidModel.from_recon(rec), ParticleAnimation(rec)
    lo, hi = np.asarray(b["lo"]) + b["inset"], np.asarray(b["hi"]) - b["inset"]
    for t in load_dataset(blob).times:
        with torch.no_grad():
            p = model.at(float(t))["means"].numpy()
        assert (p >= lo - 1e-6).all() and (p <= hi + 1e-6).all()
        assert np.allclose(anim.at(float(t))["positions"], p, atol=1e-5)
    for png in r["plots"]:
        assert (run / png).stat().st_size > 5000


def test_color_residuals_follow_a_colour_that_changes_in_time(tmp_path):
    """Colour residuals (decoder.color_residuals, not in the paper): the blob brightens from frame
    to frame; with them each frame's colour is matched (training PSNR clearly higher than with one
    colour per particle for the whole clip), the canonical frame keeps the canonical colour exactly
    (without residuals of its own), and the particles are where they were (both Chamfer directions
    under one spacing)."""
    base = np.array([0.3, 0.5, 0.8])
    root = splat_dataset(tmp_path / "ds", falling_blob(n_side=9, frames=8),
                         frame_colors=[base * (0.75 + 0.05 * f) for f in range(8)])
    res, recs = {}, {}
    for on in (True, False):
        run = tmp_path / f"run_{on}"
        reconstruct(load_dataset(root), run, small_config(decoder={"color_residuals": on, "canonical_residual": False}),
                    log=quiet)
        res[on] = evaluate(run, dataset=load_dataset(root), log=quiet)
        recs[on] = read_recon(run / "recon.h5")
    col = recs[True].decoder.color_residuals
    assert col is not None and col.shape == (recs[True].num_particles, 8, 3) and recs[False].decoder.color_residuals is None
    assert np.abs(col[:, 0]).max() == 0.0 and np.abs(col[:, -1]).mean() > 0.05  # canonical frame 0: none
    on, off = (np.array([x["psnr"] for x in res[k]["train"]["per_frame"]]) for k in (True, False))
    assert on.mean() > off.mean() + 1.5, (on, off)
    assert on[-1] > off[-1] + 3.0, (on, off)  # the frame furthest from the canonical colour
    pv = res[True]["particles_vs_gt"]
    assert pv["gt_to_recon_max_frame"] < 1.0 and pv["recon_to_gt_max_frame"] < 1.0, pv


def test_density_term_makes_the_distribution_uniform_and_fills_the_interior(blob, tmp_path):
    """Ablation: with lambda_d > 0 the per-frame SPH density spread is clearly lower than with
    lambda_d = 0, and most interior true particles have a reconstructed particle within 1 spacing."""
    res = {}
    for name, dens in (("with", 0.1), ("without", 0.0)):
        run = tmp_path / name
        cfg = small_config(loss={"density": dens})
        reconstruct(load_dataset(blob), run, cfg, log=quiet)
        res[name] = evaluate(run, dataset=load_dataset(blob), log=quiet)
    std_with = np.array([d["std"] for d in res["with"]["density"]["per_frame"]])
    std_without = np.array([d["std"] for d in res["without"]["density"]["per_frame"]])
    assert std_with.mean() < 0.8 * std_without.mean(), (std_with, std_without)
    # interior: true particles at least 1.5 spacings inside the blob's hull
    sim = load_dataset(blob).ground_truth()
    rec = FluidModel.from_recon(read_recon(tmp_path / "with" / "recon.h5"))
    covered = []
    for f in range(sim.num_frames):
        gt = sim.positions[f]
        c = gt.mean(0)
        rad = np.linalg.norm(gt - c, axis=1)
        inner = gt[rad < rad.max() - 1.5 * 2 * sim.particle_radius]
        p = rec.positions([sim.times[f]])[0].numpy()
        d = np.linalg.norm(inner[:, None] - p[None], axis=-1).min(1) / (2 * sim.particle_radius)
        covered.append((d <= 1.0).mean())
    assert min(covered) > 0.9, covered


@pytest.mark.parametrize("extra", [{}, {"decoder": {"residuals": True, "color_residuals": True, "opacity_residuals": True,
                                                   "canonical_residual": True},
                                       "lr": {"residuals_beta1": 0.0, "residuals_final": 0.2},
                                       "phases": {"residuals_from": 2, "error_sampling": 0.5, "freeze_decoder": True}}],
                         ids=["paper", "residuals+appearance+canonical+error-sampling+frozen-decoder"])
def test_resume_continues_exactly(blob, tmp_path, extra):
    """A run interrupted after a checkpoint and resumed ends where an uninterrupted run ends
    (with the decoder residuals, their own Adam momentum and error-weighted frames: their state
    is in the checkpoint)."""
    cfg = small_config(phases={"iterations": 240, **extra.get("phases", {})}, decoder=extra.get("decoder", {}),
                       lr=extra.get("lr", {}), train={"checkpoint_every": 100, "log_every": 20})
    ds = load_dataset(blob)
    a = reconstruct(ds, tmp_path / "a", cfg, log=quiet)
    # b: stop after the checkpoint at iteration 100, by a time budget hit just after it
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "b", log=quiet)
    orig = tr.step
    calls = {"n": 0}

    def stop_at_100(*a):
        if calls["n"] == 100:
            raise KeyboardInterrupt
        calls["n"] += 1
        return orig(*a)

    tr.step = stop_at_100
    with pytest.raises(KeyboardInterrupt):
        tr.run()
    if extra:  # the residuals' own momentum reaches their optimiser groups, the others keep Adam's
        assert tr.opt.group("residual_dp")["betas"][0] == 0.0 and tr.opt.group("means")["betas"][0] == 0.9
    b = reconstruct(load_dataset(blob), tmp_path / "b", cfg, resume=True, log=quiet)
    ra, rb = read_recon(tmp_path / "a" / "recon.h5"), read_recon(tmp_path / "b" / "recon.h5")
    assert a["iterations"] == b["iterations"] == 240
    assert np.allclose(ra.means, rb.means, atol=1e-5) and np.allclose(ra.decoder.features, rb.decoder.features, atol=1e-5)
    if extra:
        assert ra.decoder.residuals.shape == (len(ra.means), 8, 10) and np.abs(ra.decoder.residuals).max() > 0
        assert np.allclose(ra.decoder.residuals, rb.decoder.residuals, atol=1e-5)
        assert np.abs(ra.decoder.residuals[:, 0]).max() > 0  # the canonical frame's own residual trained
        for k in ("color_residuals", "opacity_residuals"):  # the appearance residuals trained and resumed
            a_k, b_k = getattr(ra.decoder, k), getattr(rb.decoder, k)
            assert np.abs(a_k).max() > 0 and np.allclose(a_k, b_k, atol=1e-5), k


def test_resume_refuses_another_dataset_or_config(blob, tmp_path):
    cfg = small_config(phases={"iterations": 60})
    reconstruct(load_dataset(blob), tmp_path / "r", cfg, log=quiet)
    with pytest.raises(ReconstructionError, match="another configuration"):
        reconstruct(load_dataset(blob), tmp_path / "r", small_config(phases={"iterations": 61}), resume=True, log=quiet)
    other = splat_dataset(tmp_path / "other", falling_blob(n_side=7, frames=8, seed=3))
    with pytest.raises(ReconstructionError, match="other images"):
        reconstruct(load_dataset(other), tmp_path / "r", cfg, resume=True, log=quiet)


# ---- extreme and bad input ---------------------------------------------------------------------------
def test_static_scene_has_no_decoder(tmp_path):
    sim = falling_blob(n_side=7, frames=1)
    root = splat_dataset(tmp_path / "static", sim, test_views=0)
    reconstruct(load_dataset(root), tmp_path / "run", small_config(phases={"iterations": 150}), log=quiet)
    r = read_recon(tmp_path / "run" / "recon.h5")
    assert r.decoder is None


def test_one_view_and_a_budget_of_one_particle(blob, tmp_path):
    ds = load_dataset(blob)
    ds.frames = [f for f in ds.frames if f.view_id == 2]
    m = reconstruct(ds, tmp_path / "one_view", small_config(phases={"iterations": 90}), log=quiet)
    assert m["particles"] >= 1
    m = reconstruct(load_dataset(blob), tmp_path / "one", small_config(
        phases={"iterations": 90}, model={"init_particles": 1, "max_particles": 1}), log=quiet)
    r = read_recon(tmp_path / "one" / "recon.h5")
    assert r.num_particles == 1 and np.all(np.isfinite(r.means))


def test_empty_images_give_a_clear_error(tmp_path):
    sim = falling_blob(n_side=5, frames=3)
    sim.positions[:] += np.array([0.0, 0.0, 50.0], np.float32)  # the fluid is out of every view
    sim.domain_max = (0.4, 0.4, 60.0)
    root = splat_dataset(tmp_path / "empty", sim, test_views=0)
    with pytest.raises(InputError, match="alpha masks of the canonical frame are empty"):
        reconstruct(load_dataset(root), tmp_path / "run", small_config(), log=quiet)


def test_dataset_without_alpha_starts_from_the_box(blob, tmp_path):
    import shutil

    from gf_core.data.images import read_image, write_png

    root = tmp_path / "noalpha"
    shutil.copytree(blob, root)
    for png in root.glob("*/*.png"):
        img = read_image(png)
        a = img[..., 3:4].astype(np.float32) / 255
        write_png(png, (img[..., :3].astype(np.float32) / 255 * a))  # RGB composited on black
    msgs = []
    m = reconstruct(load_dataset(root), tmp_path / "run", small_config(phases={"iterations": 120}), log=msgs.append)
    assert any("no alpha" in s for s in msgs) and m["particles"] >= 1


def test_non_finite_steps_are_skipped_then_stop_the_run(blob, tmp_path, monkeypatch):
    """A step whose loss (or gradient) is not finite changes nothing and is reported; a run of
    them stops training with a clear error. Parameters never become NaN."""
    cfg = small_config(phases={"iterations": 100}, train={"max_bad_steps": 3})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "nan", log=quiet)
    tr.initialise()
    from gf_core.recon.schedule import Plateau
    from gf_core.recon.terms import aniso

    tr.plateau = Plateau(100, 0.01)
    before = tr.model.means.detach().clone()
    monkeypatch.setattr(aniso, "anisotropy", lambda s: (s * float("nan")).sum())  # an overflowing term
    rec = tr.step()
    assert not rec["finite"] and tr.bad_steps == 1
    assert torch.equal(tr.model.means.detach(), before)  # no update
    assert all(bool(torch.isfinite(p).all()) for p in tr.model.per_particle().values())
    tr.step()
    with pytest.raises(ReconstructionError, match="3 consecutive non-finite steps"):
        tr.step()


def test_config_errors_name_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[loss]\nrgbb = 1.0\n")
    with pytest.raises(InputError, match="unknown key loss.rgbb"):
        make_config("water", bad)
    bad.write_text("[phases]\niterations = 'many'\n")
    with pytest.raises(InputError, match="phases.iterations must be a number"):
        make_config("water", bad)
    bad.write_text("[model\n")
    with pytest.raises(InputError, match="not valid TOML"):
        make_config("water", bad)
    with pytest.raises(InputError, match="unknown preset"):
        make_config("lava")
    bad.write_text("[lr]\nresiduals_beta1 = 1.0\n")
    with pytest.raises(InputError, match="lr.residuals_beta1 must be in"):
        make_config("water", bad).validate()
    for preset in ("water", "honey", "smoke"):
        assert make_config(preset).validate()
    # honey and smoke are the water preset with some keys changed
    water, honey, smoke = make_config("water"), make_config("honey"), make_config("smoke")
    assert honey.loss.aniso == smoke.loss.aniso == water.loss.aniso != ReconConfig().loss.aniso
    assert honey.decoder.residuals and smoke.phases.freeze_decoder == water.phases.freeze_decoder
    assert honey.model.init_particles != water.model.init_particles and smoke.model.sh_degree == 0


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
def test_scene_box_and_floor_options_refuse_bad_values_in_one_line(small_blob, tmp_path, capsys, argv, message):
    rc = gf_cli(["reconstruct", str(small_blob), "--out", str(tmp_path / "run"), "--quiet"] + argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "run").exists()  # refused before any work


def test_scene_box_and_floor_reach_the_trainer_and_recon_h5(small_blob, tmp_path):
    root, box = without_scene_box(small_blob, tmp_path / "nobox")
    ds = load_dataset(root)
    said = []
    # a blob that falls through the clip rests on no floor: none is seen in its masks
    tr = Trainer(quick_config(), ds, out=tmp_path / "a", log=said.append)
    tr.initialise()
    assert tr.box_source == "cameras"
    assert any("--scene-box" in s and "--floor" in s and "floor and settle terms are off" in s for s in said)
    said.clear()
    tr = Trainer(quick_config(model={"floor_estimate": "none"}), ds, out=tmp_path / "a2", log=said.append)
    tr.initialise()
    assert tr.box_source == "cameras" and any("floor and settle terms are off" in s for s in said)
    with pytest.raises(InputError, match="model.floor_estimate must be"):
        quick_config(model={"floor_estimate": "ground"})
    tr = Trainer(quick_config(model={"floor": [-0.05]}), ds, out=tmp_path / "b", log=quiet)
    tr.initialise()
    assert tr.box_source == "cameras, floor from config" and tr.model.bounds.lo[2] == pytest.approx(-0.05)
    # a floor in the dataset's own file
    p = root / "transforms_train.json"
    meta = json.loads(p.read_text())
    p.write_text(json.dumps({**meta, "floor": -0.04}))
    tr = Trainer(quick_config(), load_dataset(root), out=tmp_path / "c", log=quiet)
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
        quick_config(model={"floor": [0.0, 1.0]})


def test_cli_reconstruct_and_evaluate(blob, tmp_path, capsys):
    from gf_cli.main import main

    run = tmp_path / "cli_run"
    assert main(["reconstruct", str(blob), "--out", str(run), "--iterations", "60", "--init-particles", "300",
                 "--quiet"]) == 0
    assert (run / "recon.h5").exists() and (run / "metrics.jsonl").exists()
    assert main(["reconstruct", str(blob), "--out", str(run), "--iterations", "60", "--quiet"]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main(["evaluate", str(run)]) == 0
    ev = json.loads((run / "eval.json").read_text())
    assert math.isfinite(ev["train"]["psnr_mean"]) and "particles_vs_gt" in ev
    assert len(ev["shape"]["per_frame"]) == 8 and ev["shape"]["axis_ratio_p95_mean"] >= ev["shape"]["axis_ratio_median_mean"] >= 1
    assert main(["reconstruct", str(blob), "--out", str(run), "--device", "foo"]) == 2
    assert "unknown device 'foo'" in capsys.readouterr().err
