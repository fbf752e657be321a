"""The simulated guide (``[guide]``, recon/guide.py): the residual phase starts where a simulation
from the decoded particles carries them, and loss.residual_motion measures against it."""

import json

import numpy as np
import pytest
import torch

from gf_core.data import load_dataset
from gf_core.errors import InputError
from gf_core.formats.hdf5 import read_recon
from gf_core.recon.context import Frame
from gf_core.recon.schedule import Plateau
from gf_core.recon.terms import RESIDUAL_MOTION
from gf_core.recon.trainer import Trainer, reconstruct
from helpers import quick_config, quiet, small_config, without_scene_box

G = 9.81  # the simulators' gravity, m/s^2 along -z


def guided_trainer(blob, tmp_path, **guide):
    cfg = small_config(guide={"solver": "pbf", "start_at": "seconds", "start": 0.45, "viscosity_fit": [], **guide})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "run", log=quiet)
    tr.initialise()
    return tr


def test_the_guide_puts_the_later_frames_where_a_simulation_from_the_start_frame_carries_them(blob, tmp_path):
    """A decoder that moves every particle at one velocity (its position residuals, before the
    guide): from the start frame on, the decoded cloud's mean moves as a simulated free flight from
    that frame's position and velocity (pressure and XSPH conserve momentum); before it nothing
    changes; residual_motion is 0 on the guide itself and counts what the residuals add to it."""
    tr = guided_trainer(blob, tmp_path)
    dec, times = tr.model.decoder, tr.views.unique_times
    j0 = 5  # the first frame at or after 0.45 s (10 fps)
    assert times[j0] - times[0] == pytest.approx(0.5)
    v = torch.tensor([0.3, 0.0, 0.5])
    with torch.no_grad():  # the fluid's decoded positions pass the start frame's at v
        dec.residual_dp.copy_((torch.as_tensor(times, dtype=torch.float32)[None, :, None] - float(times[j0])) * v)
    before = [p["means"].clone() for p in tr.model.at_many(list(times))]
    tr.phase = 3
    tr.start_guide()
    with torch.no_grad():
        after = [p["means"] for p in tr.model.at_many(list(times))]
    for j in range(j0 + 1):  # up to the start frame the particles stay where they were decoded
        torch.testing.assert_close(after[j], before[j], atol=1e-5, rtol=0)
    for j in range(j0 + 1, len(times)):
        dt = float(times[j] - times[j0])
        want = v.numpy() * dt + np.array([0.0, 0.0, -0.5 * G * dt * dt])
        got = (after[j] - after[j0]).mean(0).numpy()
        np.testing.assert_allclose(got, want, atol=0.01)
        assert not torch.allclose(after[j], before[j], atol=1e-3)  # gravity: not the decoder's straight line
    assert torch.equal(tr.model.fixed["guide_dp"], dec.residual_dp.detach())
    f = Frame(tr.ctx, float(times[j0 + 1]), float(times[j0 + 1]), tr.model.at(float(times[j0 + 1])), [])
    w = {"residual_motion": 1.0}
    assert float(RESIDUAL_MOTION.frame(tr.ctx, f, w)) == 0.0
    with torch.no_grad():
        dec.residual_dp[:, j0 + 1] += tr.ctx.spacing  # one spacing along every axis at one frame
    assert float(RESIDUAL_MOTION.frame(tr.ctx, f, w)) == pytest.approx(3.0, rel=1e-4)


def test_a_ballistic_guide_flies_the_frames_before_the_start_back_under_gravity(blob, tmp_path):
    """``before = "ballistic"``: before the start frame each particle is where free flight from its
    place and velocity at the start frame puts it; from the start on, as with the decoder."""
    tr = guided_trainer(blob, tmp_path, before="ballistic")
    dec, times = tr.model.decoder, tr.views.unique_times
    j0 = 5
    v = torch.tensor([0.3, 0.0, 0.2])
    with torch.no_grad():
        dec.residual_dp.copy_((torch.as_tensor(times, dtype=torch.float32)[None, :, None] - float(times[j0])) * v)
        start = tr.model.at(float(times[j0]))["means"].clone()
    tr.phase = 3
    tr.start_guide()
    with torch.no_grad():
        raw = [p["unclamped"] for p in tr.model.at_many(list(times), with_unclamped=True)]
    torch.testing.assert_close(raw[j0], start, atol=1e-5, rtol=0)
    for j in range(j0):
        dt = float(times[j] - times[j0])
        want = start + v * dt + torch.tensor([0.0, 0.0, -0.5 * G * dt * dt])
        torch.testing.assert_close(raw[j], want, atol=1e-4, rtol=0)
    with pytest.raises(InputError, match="guide.before must be one of"):
        small_config(guide={"before": "backwards"}).validate()


def test_the_guide_follows_densification_and_checkpoints(blob, tmp_path):
    tr = guided_trainer(blob, tmp_path)
    tr.phase = 3
    tr.start_guide()
    g = tr.model.fixed["guide_dp"].clone()
    n = len(tr.model)
    keep = torch.ones(n, dtype=torch.bool)
    keep[0] = False
    per = {**tr.model.per_particle(), **tr.model.per_particle_fixed()}
    tr.opt.surgery(keep, {k: v[1:3].detach() for k, v in per.items()})  # drop particle 0, clone 1 and 2
    got = tr.model.fixed["guide_dp"]
    assert got.shape[0] == len(tr.model) == n + 1
    assert torch.equal(got[:n - 1], g[1:]) and torch.equal(got[n - 1:], g[1:3])
    tr.plateau = Plateau(tr.cfg.phases.plateau_window, tr.cfg.phases.plateau_tol)
    tr.save_checkpoint()
    back = Trainer(tr.cfg, load_dataset(blob), out=tmp_path / "run", log=quiet)
    back.load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert torch.equal(back.model.fixed["guide_dp"], got)
    assert back.guide_report == tr.guide_report and tr.guide_report["solver"] == "pbf"


def test_a_guided_run_trains_and_logs_its_simulation(blob, tmp_path):
    lines = []
    cfg = quick_config(guide={"solver": "pbf", "start_at": "seconds", "start": 0.35, "viscosity_fit": []})
    metrics = reconstruct(load_dataset(blob), tmp_path / "run", cfg, log=lines.append)
    assert any(s.startswith("guide: pbf from") for s in lines)
    r = read_recon(tmp_path / "run" / "recon.h5")
    assert r.metrics["guide"]["solver"] == "pbf" and r.metrics["guide"]["steps"] > 0
    assert np.isfinite(r.means).all()
    with pytest.raises(InputError, match="guide.solver must be one of"):
        small_config(guide={"solver": "sph"}).validate()
    with pytest.raises(InputError, match="guide.solver needs decoder.residuals"):
        small_config(guide={"solver": "pbf"}, decoder={"residuals": False, "color_residuals": False,
                                                       "time_interpolation": "decoder"},
                     phases={"freeze_decoder": False}).validate()


def test_without_a_known_container_the_guide_and_guided_coherence_are_off(small_blob, tmp_path):
    """A dataset without a scene box: the box is a guess from the cameras, whose walls are not the
    container's, so the guide is skipped with a line that says how to give the container; the run
    trains on and recon.h5 has no guide report. loss.coherence with coherence_guided (the water
    preset's) is off there too, said in one line and never computed; with coherence_guided = false
    it acts without the guide. The same data with its box given is guided, and coherence acts from
    phase 2."""
    root, box = without_scene_box(small_blob, tmp_path / "nobox")
    lines = []

    def terms_logged(run):
        rows = [json.loads(x) for x in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]
        return {ph: set().union(*[set(r["terms"]) for r in rows if r["phase"] == ph]) for ph in (2, 3)}

    over = dict(phases={"iterations": 90}, train={"log_every": 1},
                guide={"solver": "pbf", "start_at": "seconds", "start": 0.0, "viscosity_fit": []},
                loss={"coherence": 0.01, "coherence_from": 2, "coherence_every": 1, "coherence_guided": True})
    reconstruct(load_dataset(root), tmp_path / "guess", quick_config(**over), log=lines.append)
    assert any(s.startswith("guide: not simulated: the container is not known") and "--scene-box" in s for s in lines)
    assert sum(s.startswith("loss.coherence is off: it acts with the simulated guide only") and "--scene-box" in s
               for s in lines) == 1
    assert not any(s.startswith("guide: pbf from") for s in lines)
    assert not any("coherence" in t for t in terms_logged("guess").values())
    r = read_recon(tmp_path / "guess" / "recon.h5")
    assert "guide" not in r.metrics and np.isfinite(r.means).all()

    lines.clear()
    loose = dict(over, loss=dict(over["loss"], coherence_guided=False))
    reconstruct(load_dataset(root), tmp_path / "loose", quick_config(**loose), log=lines.append)
    assert not any(s.startswith("loss.coherence is off") for s in lines)
    assert all("coherence" in t for t in terms_logged("loose").values())

    lines.clear()
    given = quick_config(**dict(over, model={"scene_box": box}))
    reconstruct(load_dataset(root), tmp_path / "given", given, log=lines.append)
    assert any(s.startswith("guide: pbf from") for s in lines)
    assert not any(s.startswith("loss.coherence is off") for s in lines)
    assert all("coherence" in t for t in terms_logged("given").values())
    assert read_recon(tmp_path / "given" / "recon.h5").metrics["guide"]["steps"] > 0


def test_a_contact_start_simulates_from_the_frame_before_the_fluid_meets_the_floor(blob, tmp_path):
    """``start_at = "contact"``: the decoded fluid sinks at a constant speed; the simulation starts
    at the last frame before 5 % of the particles come within a spacing of the box's floor, the
    frames up to it keep their positions and the report names the contact. Fluid that never comes
    near a face is not simulated (nothing changes)."""
    tr = guided_trainer(blob, tmp_path, start_at="contact")
    dec, times, model = tr.model.decoder, tr.views.unique_times, tr.model
    with torch.no_grad():
        z = model.at(float(times[0]))["means"][:, 2]
    lo_z, sp = float(model._lo[2]), tr.ctx.spacing
    want = 6  # the frame at which the lowest particles are to reach the floor
    drop = (float(torch.quantile(z, 0.5)) - lo_z) / float(times[want] - times[0])  # half the fluid there at frame 6
    t = torch.as_tensor(times - times[0], dtype=torch.float32)
    with torch.no_grad():
        dec.residual_dp.copy_(torch.tensor([0.0, 0.0, -drop]) * t[None, :, None])
        decoded = torch.stack([p["means"] for p in model.at_many(list(times))])
    gap = decoded[..., 2] - lo_z
    contact = int(torch.nonzero((gap < sp).float().mean(-1) >= 0.05)[0, 0])
    assert 0 < contact <= want
    before = decoded.clone()
    tr.phase = 3
    tr.start_guide()
    rep = tr.guide_report
    assert rep["start_at"] == "contact" and rep["contact_frame"] == contact and rep["start_frame"] == contact - 1
    assert rep["frames"] == len(times) - contact
    with torch.no_grad():
        after = torch.stack([p["means"] for p in model.at_many(list(times))])
    torch.testing.assert_close(after[:contact], before[:contact], atol=1e-5, rtol=0)
    assert not torch.allclose(after[contact:], before[contact:], atol=1e-3)

    far = guided_trainer(blob, tmp_path / "far", start_at="contact")  # still, in the middle of the box
    with torch.no_grad():
        far.model.decoder.residual_dp.zero_()
        mid = 0.5 * (far.model._lo + far.model._hi)
        far.model.means.copy_(mid + 0.1 * (far.model.means - far.model.means.mean(0)))  # a tenth of its size
    far.phase = 3
    far.start_guide()
    assert far.guide_report["contact_frame"] is None and far.guide_report["frames"] == 0
    assert torch.equal(far.model.fixed["guide_dp"], torch.zeros_like(far.model.fixed["guide_dp"]))
    with pytest.raises(InputError, match="guide.start_at must be one of"):
        small_config(guide={"start_at": "impact"}).validate()


def test_the_start_velocities_average_the_shuffle_out_and_keep_a_common_motion():
    """Neighbour-averaged start velocities: a common velocity is kept exactly; a shuffle of
    +-1 m/s between neighbours on top of it is averaged down to a fraction."""
    from gf_core.recon.guide import smoothed_velocities

    g = torch.stack(torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.01
    common = torch.tensor([0.2, -0.1, -1.5]).expand(g.shape[0], 3)
    torch.testing.assert_close(smoothed_velocities(g, common.clone(), 0.02), common)
    sign = ((g / 0.01).round().sum(-1) % 2 * 2 - 1)[:, None]  # a checkerboard: every neighbour the other way
    shuffled = common + sign * torch.tensor([1.0, 1.0, 1.0])
    got = smoothed_velocities(g, shuffled, 0.02)
    interior = ((g > 0.015) & (g < 0.055)).all(-1)
    assert float((got - common)[interior].norm(dim=-1).max()) < 0.35 * float(np.sqrt(3))


def test_the_viscosity_fit_picks_the_viscosity_the_decoded_motion_follows(blob, tmp_path):
    """``guide.viscosity_fit``: the decoded fluid lands on the floor at 2 m/s, and from the start
    frame on it follows a PBF continuation at a known viscosity (water's or a thick liquid's). Of
    the candidates, the fit chooses the one the motion follows, simulates with it and reports every
    candidate's Chamfer distance (not 0 for the one followed: its start velocity is measured from
    the decoded frames either side, as in a run)."""
    from gf_core.recon.guide import GuideConfig, simulate_guide

    tr = guided_trainer(blob, tmp_path)
    dec, times, model = tr.model.decoder, tr.views.unique_times, tr.model
    j0 = 5
    with torch.no_grad():
        z = model.at(float(times[j0]))["means"][:, 2]
    lift = float(model._lo[2]) + 0.5 * tr.ctx.spacing - float(z.min())  # the lowest particle half a spacing up
    t = torch.as_tensor(times - times[j0], dtype=torch.float32)
    landing = torch.stack([torch.zeros_like(t), torch.zeros_like(t), lift - 2.0 * t], -1)[None]  # (1, F, 3)
    for nu in (0.0, 0.2):
        with torch.no_grad():
            dec.residual_dp.copy_(landing.expand_as(dec.residual_dp))
        follow, _ = simulate_guide(model, times, GuideConfig(solver="pbf", start=0.45, viscosity=nu),
                                   spacing=tr.ctx.spacing, log=quiet)
        with torch.no_grad():
            dec.residual_dp.copy_(follow)
        lines = []
        fit = GuideConfig(solver="pbf", start=0.45, viscosity_fit=[0.0, 0.2], fit_frames=2)
        fitted, report = simulate_guide(model, times, fit, spacing=tr.ctx.spacing, log=lines.append)
        scores = {f["viscosity"]: f["chamfer"] for f in report["viscosity_fit"]}
        assert report["viscosity"] == nu and scores[nu] < 0.8 * scores[0.2 - nu], scores
        # the chosen candidate's simulation goes on from the fit's frames: the same guide as one run
        chosen, alone = simulate_guide(model, times, GuideConfig(solver="pbf", start=0.45, viscosity=nu),
                                       spacing=tr.ctx.spacing, log=quiet)
        assert torch.equal(fitted, chosen)
        one = GuideConfig(solver="pbf", start=0.45, viscosity_fit=[nu], fit_frames=2)
        assert simulate_guide(model, times, one, spacing=tr.ctx.spacing, log=quiet)[1]["steps"] == alone["steps"]
        assert any(s.startswith("guide: viscosity fit over 2 frames") and f"; {nu:g} chosen" in s for s in lines)
    off = small_config(guide={"solver": "none"}).validate()  # turning the guide off needs no other key
    assert off.guide.viscosity_fit == [0.0, 0.01, 0.1]
    with pytest.raises(InputError, match=r"guide.viscosity_fit must be in \[0, 1000\]"):
        small_config(guide={"solver": "pbf", "viscosity_fit": [0.0, -0.1]}).validate()
