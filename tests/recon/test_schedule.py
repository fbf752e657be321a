"""The schedule (phases, weight ramps, learning rates, the time budget) and what a step draws."""

import math

import numpy as np
import pytest

from gf_core.data import load_dataset
from gf_core.errors import InputError
from gf_core.formats.hdf5 import read_recon
from gf_core.recon import schedule
from gf_core.recon.config import make_config
from gf_core.recon.trainer import Trainer, reconstruct
from helpers import quick_config, quiet, small_config


def test_weight_schedule_follows_the_paper():
    # Table 1 of the paper: the final weights of Eq. 11
    TABLE1_WEIGHTS = {"rgb": 0.2, "ssim": 0.1, "density": 0.1, "aniso": 0.1, "volume": 0.1, "opacity": 0.01, "color": 1.0}
    from gf_core.recon.config import LossConfig

    assert all(getattr(LossConfig(), k) == v for k, v in TABLE1_WEIGHTS.items())  # the defaults are Table 1's
    cfg = make_config("water", overrides={"loss": dict(TABLE1_WEIGHTS)})  # (the water preset lowers lambda_a, lambda_v)
    w1 = schedule.loss_weights(cfg, 1, 1.0)
    assert w1["density"] == 0 and w1["aniso"] == pytest.approx(0.01) and w1["volume"] == pytest.approx(0.01)
    assert schedule.loss_weights(cfg, 2, 0.0)["density"] == 0.0
    assert schedule.loss_weights(cfg, 2, 1.0)["density"] == pytest.approx(0.01)
    w3 = schedule.loss_weights(cfg, 3, 1.0)
    assert (w3["density"], w3["aniso"], w3["volume"], w3["rgb"], w3["ssim"], w3["opacity"], w3["color"]) == \
        pytest.approx((0.1, 0.1, 0.1, 0.2, 0.1, 0.01, 1.0))


def test_a_time_budget_is_split_by_time_fractions(blob, tmp_path):
    """phases.time_fractions: with a time budget the phases end at these shares of the seconds;
    [] splits the seconds like the iterations (phases.fractions)."""
    cfg = small_config(phases={"time_fractions": [0.1, 0.5, 0.4]}, train={"time_budget_s": 100.0})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "a", log=quiet)
    assert [schedule.phase_deadline(cfg, k, tr.static) for k in (1, 2, 3)] == pytest.approx([10.0, 60.0, 100.0])
    assert schedule.phase_cap(cfg, 1, tr.static) == round(900 * 0.2)  # the iteration caps keep phases.fractions
    cfg = small_config(phases={"time_fractions": [], "fractions": [0.2, 0.45, 0.35]}, train={"time_budget_s": 100.0})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "b", log=quiet)
    assert [schedule.phase_deadline(cfg, k, tr.static) for k in (1, 2, 3)] == pytest.approx([20.0, 65.0, 100.0])
    cfg.train.time_budget_s = 0.0
    assert schedule.phase_deadline(cfg, 1, tr.static) == math.inf
    with pytest.raises(InputError, match="time_fractions must be"):
        small_config(phases={"time_fractions": [0.5, 0.5]}).validate()


def test_residual_rates_decay_over_phase_3_to_residuals_final(blob, tmp_path):
    """lr.residuals_final: every residual group's rate (pose and colour) falls exponentially over
    phase 3 to that fraction; the other groups' rates do not follow it; earlier phases are untouched."""
    cfg = small_config(decoder={"residuals": True, "color_residuals": True},
                       lr={"residuals_final": 0.1, "residuals": 3.0}, phases={"residuals_from": 2})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path / "run", log=quiet)
    tr.initialise()
    names = [n for n in tr.base_lrs if n.startswith("residual_")]
    assert sorted(names) == ["residual_dc", "residual_dp", "residual_dr", "residual_ds"]
    assert tr.base_lrs["residual_dc"] == pytest.approx(3.0 * cfg.lr.sh_dc)
    tr.phase = 2
    tr.set_rates(0.5, 0.7)
    assert all(tr.opt.group(n)["lr"] == pytest.approx(tr.base_lrs[n]) for n in names)
    tr.phase = 3
    for prog, f in ((0.0, 1.0), (0.5, 0.1 ** 0.5), (1.0, 0.1)):
        tr.set_rates(0.8, prog)
        for n in names:
            assert tr.opt.group(n)["lr"] == pytest.approx(f * tr.base_lrs[n]), (n, prog)
        assert tr.opt.group("sh_dc")["lr"] == pytest.approx(cfg.lr.canonical_dynamic * tr.base_lrs["sh_dc"])
    with pytest.raises(InputError, match="lr.residuals_final must be in"):
        small_config(lr={"residuals_final": 0.0}).validate()


def test_error_sampling_starts_at_its_phase(blob, tmp_path):
    """phases.error_sampling draws frames by their image error from phases.error_sampling_from on,
    uniformly before it (every draw is the one bad frame at share 1 from that phase)."""
    cfg = small_config(phases={"error_sampling": 1.0, "error_sampling_from": 3})
    tr = Trainer(cfg, load_dataset(blob), out=tmp_path, log=quiet)
    times = tr.views.unique_times
    tr.sampler.frame_err = np.full(len(times), 1e-6)
    tr.sampler.frame_err[5] = 1.0
    drawn = [t for _ in range(40) for t in tr.sampler.times(2, schedule.window_width(cfg, 2, 1.0))]
    assert len(set(drawn)) >= 5  # uniform over the 8 frames in phase 2
    drawn = [t for _ in range(40) for t in tr.sampler.times(3, schedule.window_width(cfg, 3, 0.5))]
    assert set(drawn) == {float(times[5])}
    with pytest.raises(InputError, match="error_sampling_from"):
        small_config(phases={"error_sampling_from": 1})


# ---- the whole budget -------------------------------------------------------------------------------
def test_a_run_with_a_time_budget_uses_it_all_and_says_why_each_phase_ended(small_blob, tmp_path):
    """With a time budget the iteration caps do not end a phase (here phases.iterations is far too
    small for the seconds): every phase ends at its share of the time, and the run uses >= 95 % of it."""
    budget = 12.0
    said = []
    cfg = quick_config(phases={"iterations": 15}, train={"time_budget_s": budget, "eval_every": 10_000})
    m = reconstruct(load_dataset(small_blob), tmp_path / "run", cfg, log=said.append)
    assert m["wall_s"] >= 0.95 * budget
    assert m["iterations"] > 15
    ends = m["phase_ends"]
    assert [e["phase"] for e in ends] == [1, 2, 3]
    assert all("time budget" in e["reason"] for e in ends)
    assert sum("phase 3 ends" in s and "time budget" in s for s in said) == 1
    assert read_recon(tmp_path / "run" / "recon.h5").metrics["phase_ends"] == ends
    # without a budget the caps end the phases, and the log says so
    m = reconstruct(load_dataset(small_blob), tmp_path / "run2", quick_config(phases={"iterations": 60}), log=quiet)
    assert m["iterations"] == 60 and all("iteration cap" in e["reason"] for e in m["phase_ends"])


def test_the_native_build_is_not_part_of_the_time_budget(small_blob, tmp_path, monkeypatch):
    """A first use compiles the native extension (a minute or so on a fresh checkout): that is done
    before the clock of the time budget starts. Here the first load takes 4 s; the first logged
    step still comes within a second or two of the start."""
    import json
    import time

    from gf_core import native

    real, calls = native.load, []

    def slow_first_load():
        if not calls:
            time.sleep(4.0)
        calls.append(1)
        return real()

    monkeypatch.setattr(native, "load", slow_first_load)
    cfg = quick_config(phases={"iterations": 15}, train={"time_budget_s": 8.0, "eval_every": 10_000, "log_every": 1})
    m = reconstruct(load_dataset(small_blob), tmp_path / "run", cfg, log=quiet)
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert calls and rows[0]["wall_s"] < 2.0, rows[0]
    assert m["wall_s"] >= 0.95 * 8.0


def test_without_a_budget_a_phase_still_improving_at_its_cap_goes_on_to_its_plateau(small_blob, tmp_path):
    """Without a time budget the caps set the schedule, not the end: a phase whose image loss still
    improves at its cap goes on until the plateau test ends it, at most phases.limit_factor x its
    cap. The plateau test watches the loss only once the ramps (and phase 2's widening time window)
    are done, so a plateau comes no earlier than one window after them. Here the window (30
    iterations) is longer than phase 1's cap (12), so phase 1 cannot end at its cap."""
    window, factor = 30, 4.0
    cfg = quick_config(phases={"iterations": 60, "limit_factor": factor, "plateau_window": window},
                       train={"eval_every": 10_000})
    said = []
    m = reconstruct(load_dataset(small_blob), tmp_path / "run", cfg, log=said.append)
    tr = Trainer(cfg, load_dataset(small_blob), out=tmp_path / "probe", log=quiet)
    caps = [schedule.phase_cap(cfg, k, tr.static) for k in (1, 2, 3)]
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
