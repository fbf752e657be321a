"""The time decoder (paper Eq. 4), its per-frame residuals and their interpolation between the
training frames (smooth motion), reduced precision, times outside the clip."""


import numpy as np
import pytest
import torch

from gf_core.errors import InputError
from gf_core.formats.decoder_np import NumpyDecoder, hermite_coefficients
from gf_core.recon.decoder import Decoder, DecoderConfig, TimeMap
from gf_core.recon.decoder import mlp_low_precision
from helpers import small_config


# ---- the decoder (Eq. 4) ---------------------------------------------------------------------------
def random_decoder(n=37, seed=0, dtype=torch.float32, **kw):
    torch.manual_seed(seed)
    d = Decoder(n, DecoderConfig(**kw), dtype=dtype)
    with torch.no_grad():
        for p in d.parameters():
            p.normal_(0, 0.1)
    return d


def test_decoder_starts_at_zero_and_is_exact_at_the_canonical_time():
    d = Decoder(20, DecoderConfig())
    for tau in (0.0, 0.3, 1.0):
        out = d(tau)
        assert all(float(v.abs().max()) == 0.0 for v in out.values())  # zero-initialised
    d = random_decoder(canonical_time=0.4)
    out = d(0.4)
    assert all(float(v.abs().max()) == 0.0 for v in out.values())      # exactly A^0 at tau0
    assert float(d(0.9)["dp"].abs().max()) > 1e-3


@pytest.mark.parametrize("n", [1, 50, 3000])
def test_decoder_velocity_matches_finite_differences(n):
    d = random_decoder(n, n_freqs=4, dtype=torch.float64)
    tm = TimeMap(1.0, 3.0)
    for t in (1.2, 2.0, 2.7):
        with torch.no_grad():
            v = d(tm.tau(t), with_velocity=True)["vp"] / tm.duration
            eps = 1e-6
            fd = (d(tm.tau(t + eps))["dp"] - d(tm.tau(t - eps))["dp"]) / (2 * eps)
        # a particle whose ReLU switches within eps of t differs: the derivative has a kink there
        close = torch.isclose(v, fd, rtol=1e-6, atol=1e-7).all(-1)
        assert float(close.double().mean()) >= 0.99 and (n > 100 or bool(close.all()))


def test_frozen_decoder_reuses_its_output_and_trains_only_the_residuals(monkeypatch):
    """phases.freeze_decoder: while frozen, (tau - tau0) Phi is computed once per time and equals
    the live output; no gradient reaches theta or Phi, the residuals still get theirs; new
    features (densify/prune) drop what was kept."""
    torch.manual_seed(1)
    d = Decoder(30, DecoderConfig(residuals=True), knots=[0.0, 0.25, 0.5, 0.75, 1.0], dtype=torch.float64)
    with torch.no_grad():
        for p in d.parameters():
            p.normal_(0, 0.1)
    taus = [0.25, 0.6]
    live = d.forward_many(taus)
    d.freeze(True)
    first = d.forward_many(taus)
    for k in live:
        assert torch.allclose(first[k], live[k], rtol=0, atol=1e-12), k
    calls = []
    orig = d._mlp
    monkeypatch.setattr(d, "_mlp", lambda *a: calls.append(1) or orig(*a))
    out = d.forward_many([0.6, 0.25, 0.6])          # times seen before: no MLP pass
    assert not calls and torch.allclose(out["dp"][1], live["dp"][0], rtol=0, atol=1e-12)
    sum(v.square().sum() for v in out.values()).backward()
    assert d.features.grad is None and all(p.grad is None for p in d.mlp_parameters())
    assert float(d.residual_dp.grad.abs().max()) > 0
    d.forward_many([0.9])                           # a new time: one pass for it alone
    assert len(calls) == 1
    d.replace_features(d.features.detach() * 2)     # other particles: recomputed
    again = d.forward_many(taus)
    assert len(calls) == 2
    d.freeze(False)
    assert torch.allclose(again["dp"], d.forward_many(taus)["dp"], rtol=0, atol=1e-12)
    assert not torch.allclose(again["dp"], live["dp"])
    d.forward_many(taus)["dp"].sum().backward()     # unfrozen: Phi trains again
    assert d.features.grad is not None and d.layers[-1].weight.grad is not None


def test_bfloat16_training_passes_stay_close_to_float32_and_the_rest_is_float32():
    """train.mlp_precision: with Decoder.mlp_dtype = bfloat16, passes that record gradients run the
    first and hidden layers in bfloat16 (close to float32, same gradient direction); passes without
    gradients and velocities are the float32 decoder exactly."""
    torch.manual_seed(3)
    d = Decoder(400, DecoderConfig(residuals=True), knots=[0.0, 0.5, 1.0])
    with torch.no_grad():
        for p in d.parameters():
            p.normal_(0, 0.1)
    taus = [0.3, 0.8]
    ref = d.forward_many(taus)
    g_ref = torch.autograd.grad(ref["dp"].square().sum(), d.features)[0]
    d.mlp_dtype = torch.bfloat16
    low = d.forward_many(taus)
    g_low = torch.autograd.grad(low["dp"].square().sum(), d.features)[0]
    for k in ref:
        assert low[k].dtype == torch.float32
        err = float((low[k] - ref[k]).norm() / ref[k].norm())
        assert 0 < err < 0.02, (k, err)      # bf16 (8-bit mantissa) rounding, and not float32 by accident
    assert float(torch.nn.functional.cosine_similarity(g_low.flatten(), g_ref.flatten(), dim=0)) > 0.99
    with torch.no_grad():
        exact = d.forward_many(taus)
    assert all(torch.equal(exact[k], ref[k].detach()) for k in ref)
    vel = d.forward_many(taus, with_velocity=True)
    assert torch.equal(vel["dp"], ref["dp"])
    assert not mlp_low_precision("auto", "cuda") and not mlp_low_precision("float32", "cpu")
    assert mlp_low_precision("bfloat16", "cpu")
    with pytest.raises(InputError, match="train.mlp_precision must be auto, float32 or bfloat16"):
        small_config(train={"mlp_precision": "half"}).validate()


def test_time_outside_the_clip_is_clamped_with_a_warning_or_refused():
    tm = TimeMap(0.0, 1.0)
    with pytest.warns(RuntimeWarning, match="outside the reconstructed clip"):
        assert tm.tau(1.5) == 1.0
    with pytest.raises(InputError, match="outside"):
        TimeMap(0.0, 1.0, policy="error").tau(-0.1)


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
    from gf_core.formats.decoder_np import ParticleAnimation
    from gf_core.recon.model import Bounds, FluidModel
    from gf_core.recon.decoder import TimeMap

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
    from gf_core.recon.decoder import Decoder as D

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


def test_wall_gradient_reaches_a_held_coordinate_only_back_inside():
    """model.wall_gradient = "inward": a decoded position held at a face of the box still gets the
    gradient that would move it back inside, not one that pushes it further out; "none" gets none."""
    from gf_core.recon.decoder import TimeMap
    from gf_core.recon.model import Bounds, FluidModel

    means = torch.tensor([[0.0, 0.0, -0.05], [0.0, 0.0, -0.05], [0.0, 0.0, 0.0]])  # two below the floor, one inside
    n = means.shape[0]

    def grad_z(mode, pull):
        model = FluidModel(means.clone(), torch.full((n, 3), -4.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                           torch.zeros(n), torch.full((n, 1, 3), 0.5),
                           bounds=Bounds.for_box([-0.02] * 3, [0.02] * 3, 0.01, 0.0), time_map=TimeMap(0.0, 1.0))
        model.wall_gradient = mode
        z = model.at(None)["means"][:, 2]
        assert torch.allclose(z, torch.tensor([-0.02, -0.02, 0.0]))  # the forward clamp is the same either way
        (z * torch.as_tensor(pull)).sum().backward()  # the loss falls as z rises where pull < 0
        return model.means.grad[:, 2]

    pull = [-1.0, 1.0, 1.0]  # the first held particle is wanted higher, the second lower
    assert torch.equal(grad_z("inward", pull), torch.tensor([-1.0, 0.0, 1.0]))
    assert torch.equal(grad_z("none", pull), torch.tensor([0.0, 0.0, 1.0]))
    with pytest.raises(InputError, match="wall_gradient"):
        from gf_core.recon.config import make_config
        cfg = make_config("water")
        cfg.model.wall_gradient = "outward"
        cfg.validate()
