"""The numpy decoder (the Blender extension's) equals the torch decoder; time mapping; no torch."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from gf_core.formats.decoder_np import NumpyDecoder, ParticleAnimation, TimeMap
from gf_core.errors import FormatError, InputError
from gf_core.formats.hdf5 import ReconData, read_recon, write_recon
from gf_core.recon.decoder import Decoder, DecoderConfig


def trained_like(n, seed=0, **cfg):
    """A decoder with non-zero weights everywhere (as after training)."""
    torch.manual_seed(seed)
    dec = Decoder(n, DecoderConfig(**cfg))
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
        dec.layers[-1].bias.normal_(0.0, 0.01)
    return dec


@pytest.mark.parametrize("n", [1, 7, 300, 20000])
@pytest.mark.parametrize("cfg", [{}, {"canonical_time": 0.4, "n_freqs": 3, "hidden_layers": 2, "hidden_width": 32},
                                 {"include_input": False, "feature_dim": 8}])
def test_numpy_decoder_equals_torch(n, cfg):
    dec = trained_like(n, **cfg)
    nd = NumpyDecoder(dec.to_data(), block=4096)
    for tau in (0.0, 0.13, 0.4, 0.77, 1.0):
        with torch.no_grad():
            ref = dec(tau, with_velocity=True)
        got = nd(tau, with_velocity=True)
        for k in ("dp", "ds", "dr"):
            assert got[k].dtype == np.float32
            np.testing.assert_allclose(got[k], ref[k].numpy(), rtol=0, atol=1e-5, err_msg=f"{k} at tau {tau}")
        # d/dtau has a kink where a ReLU input crosses 0: rounding may put a rare particle on the
        # other side; all others agree to float32 precision
        dv = np.abs(got["vp"] - ref["vp"].numpy()).max(1)
        assert np.sum(dv >= 1e-4) <= max(1, n // 1000), (tau, dv.max())


def test_velocity_is_the_time_derivative():
    """The analytic velocity against central differences of the same decoder in float64."""
    dec = trained_like(50, canonical_time=0.2)
    nd = NumpyDecoder(dec.to_data())
    dec64 = Decoder.from_data(dec.to_data(), dtype=torch.float64)
    for tau in (0.1, 0.5, 0.9):
        e = 1e-6
        with torch.no_grad():
            fd = ((dec64(tau + e)["dp"] - dec64(tau - e)["dp"]) / (2 * e)).numpy()
        dv = np.abs(nd(tau, with_velocity=True)["vp"] - fd).max(1)
        # a ReLU kink inside [tau - e, tau + e] may spoil one particle
        assert np.sum(dv > 1e-4 * (1 + np.abs(fd).max(1))) <= 1, dv.max()


def with_residuals(n, knots, canonical_time, seed=0):
    torch.manual_seed(seed)
    dec = Decoder(n, DecoderConfig(canonical_time=canonical_time, residuals=True, n_freqs=3, hidden_width=32),
                  knots=knots)
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
        for p in dec.residuals().values():
            p.normal_(0.0, 0.05)
    return dec


def test_residuals_numpy_equals_torch_exact_at_the_canonical_time_and_velocity():
    """Decoder residuals (not in the paper): linear between the knots, zero at the canonical
    time, the same in numpy; the velocity is the derivative (away from knots and ReLU kinks)."""
    knots = np.linspace(0.0, 1.0, 7)
    dec = with_residuals(300, knots, canonical_time=float(knots[2]))
    nd = NumpyDecoder(dec.to_data())
    dec64 = Decoder.from_data(dec.to_data(), dtype=torch.float64)
    with torch.no_grad():
        at0 = dec(float(knots[2]))
    assert all(float(v.abs().max()) == 0.0 for v in at0.values())
    for tau in (0.0, 0.05, float(knots[3]), 0.61, 1.0):
        with torch.no_grad():
            ref = dec(tau, with_velocity=True)
        got = nd(tau, with_velocity=True)
        for k in ("dp", "ds", "dr"):
            np.testing.assert_allclose(got[k], ref[k].numpy(), rtol=0, atol=1e-5, err_msg=f"{k} at {tau}")
    # the residuals move the particles: without them the same decoder gives other positions
    plain = Decoder.from_data(dec.to_data())
    plain.knots = None
    with torch.no_grad():
        assert float((plain(0.61)["dp"] - dec(0.61)["dp"]).abs().max()) > 1e-3
    for tau in (0.1, 0.55, 0.9):
        e = 1e-7
        with torch.no_grad():
            fd = ((dec64(tau + e)["dp"] - dec64(tau - e)["dp"]) / (2 * e)).numpy()
            an = dec64(tau, with_velocity=True)["vp"].numpy()
        dv = np.abs(an - fd).max(1)
        assert np.sum(dv > 1e-5 * (1 + np.abs(fd).max(1))) <= 1, dv.max()
        assert np.sum(np.abs(nd(tau, with_velocity=True)["vp"] - an).max(1) > 1e-3 * (1 + np.abs(an).max(1))) <= 1


def test_recon_with_residuals_is_version_2_and_round_trips(tmp_path):
    import h5py
    r = make_recon()
    write_recon(tmp_path / "v1.h5", r)
    with h5py.File(tmp_path / "v1.h5") as f:
        assert int(f.attrs["version"]) == 1  # no residuals: readable by the toolkit before them
    knots = np.linspace(0.0, 1.0, 5)
    r.decoder = with_residuals(40, knots, 0.0).to_data()
    write_recon(tmp_path / "v2.h5", r)
    with h5py.File(tmp_path / "v2.h5") as f:
        assert int(f.attrs["version"]) == 2
    back = read_recon(tmp_path / "v2.h5")
    np.testing.assert_array_equal(back.decoder.residuals, r.decoder.residuals)
    np.testing.assert_array_equal(back.decoder.residual_knots, knots)
    a = ParticleAnimation(back).at(0.3, velocity=True)
    b = ParticleAnimation(r).at(0.3, velocity=True)
    np.testing.assert_allclose(a["positions"], b["positions"], atol=1e-6)
    r.decoder.residuals = r.decoder.residuals[:, :4]
    with pytest.raises(Exception, match="residuals must have shape"):
        write_recon(tmp_path / "bad.h5", r)


def test_appearance_residuals_numpy_equals_torch_and_round_trip_as_version_3(tmp_path):
    """Colour and opacity residuals (not in the paper): the base colour (degree-0 SH) and the logit
    opacity piecewise linear in time at the pose residuals' knots, zero at the canonical time; the
    torch model, the numpy decoder (Blender extension) and a recon.h5 round trip give the same
    colours and opacities; geometry is unchanged."""
    import h5py
    from gf_core.recon.model import FluidModel
    n, knots = 40, np.linspace(0.0, 1.0, 5)
    torch.manual_seed(3)
    dec = Decoder(n, DecoderConfig(residuals=True, color_residuals=True, opacity_residuals=True, n_freqs=3,
                                   hidden_width=32, canonical_time=float(knots[1])), knots=knots, channels=3)
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
        for name, p in dec.residuals().items():  # small pose changes: the particles stay in the box
            p.normal_(0.0, 0.3 if name in ("residual_dc", "residual_do") else 0.003)
    assert dec.residual_dc.shape == (n, 5, 3) and dec.residual_do.shape == (n, 5, 1)
    r = make_recon(n, t=(0.0, 2.0))
    r.decoder = dec.to_data()
    write_recon(tmp_path / "v3.h5", r)
    with h5py.File(tmp_path / "v3.h5") as f:
        assert int(f.attrs["version"]) == 3
    back = read_recon(tmp_path / "v3.h5")
    np.testing.assert_array_equal(back.decoder.color_residuals, r.decoder.color_residuals)
    np.testing.assert_array_equal(back.decoder.opacity_residuals, r.decoder.opacity_residuals)
    assert back.decoder.opacity_residuals.shape == (n, 5)
    model, anim = FluidModel.from_recon(back), ParticleAnimation(back)
    assert anim.color_varies and anim.opacity_varies
    for t in (0.0, 0.5, 0.77, 1.3, 2.0):  # 0.5 s is the canonical time (tau 0.25)
        with torch.no_grad():
            ref = model.at(t)
        got = anim.at(t)
        np.testing.assert_allclose(got["sh"], ref["sh"].numpy(), rtol=0, atol=1e-5, err_msg=f"sh at {t}")
        np.testing.assert_allclose(got["positions"], ref["means"].numpy(), rtol=0, atol=1e-5)
        np.testing.assert_allclose(got["opacities"], ref["opacities"].numpy(), rtol=0, atol=1e-6)
        np.testing.assert_array_equal(got["sh"][:, 1:], back.sh[:, 1:])  # only the base colour changes
        assert got["colors"].shape == (n, 3) and 0 <= got["colors"].min() and got["colors"].max() <= 1
    np.testing.assert_array_equal(anim.at(0.5)["sh"], back.sh)  # exactly the canonical look at tau0
    np.testing.assert_array_equal(anim.at(0.5)["logit_opacity"], back.logit_opacity)
    assert np.abs(anim.at(1.3)["sh"][:, 0] - back.sh[:, 0]).max() > 0.05
    assert np.abs(anim.at(1.3)["opacities"] - anim.opacity).max() > 0.01
    # without appearance residuals the file stays version 2 and the look is the same at every time
    r.decoder.color_residuals = r.decoder.opacity_residuals = None
    write_recon(tmp_path / "v2.h5", r)
    with h5py.File(tmp_path / "v2.h5") as f:
        assert int(f.attrs["version"]) == 2
    plain = ParticleAnimation(read_recon(tmp_path / "v2.h5"))
    assert not plain.color_varies and not plain.opacity_varies
    np.testing.assert_array_equal(plain.at(1.3)["sh"], back.sh)
    np.testing.assert_array_equal(plain.at(1.3)["opacities"], plain.opacity)
    r.decoder.color_residuals = back.decoder.color_residuals[:, :, :1]
    with pytest.raises(Exception, match="color_residuals must have shape"):
        write_recon(tmp_path / "bad.h5", r)
    r.decoder.color_residuals = None
    r.decoder.opacity_residuals = back.decoder.opacity_residuals[:, :4]
    with pytest.raises(Exception, match="opacity_residuals must have shape"):
        write_recon(tmp_path / "bad.h5", r)
    for k in ("color_residuals", "opacity_residuals"):
        with pytest.raises(InputError, match=f"{k} need residuals"):
            DecoderConfig(**{k: True}).validate()


def test_canonical_residual_moves_the_canonical_frame_and_round_trips_as_version_4(tmp_path):
    """With residuals of the canonical frame's own (Delta A = (tau - tau0) Phi + R(tau)), the
    canonical frame is A^0 + R(tau0): torch model, numpy decoder and a recon.h5 round trip (version 4)
    agree at and between the knots, positions and velocities, and a reader refuses the encoding in
    an older version."""
    import h5py
    from gf_core.recon.model import FluidModel
    n, knots = 40, np.linspace(0.0, 1.0, 5)
    torch.manual_seed(4)
    dec = Decoder(n, DecoderConfig(residuals=True, color_residuals=True, canonical_residual=True, n_freqs=3,
                                   hidden_width=32, canonical_time=float(knots[0])), knots=knots, channels=3)
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
        for name, p in dec.residuals().items():
            p.normal_(0.0, 0.3 if name == "residual_dc" else 0.003)
    r = make_recon(n, t=(0.0, 2.0))
    r.decoder = dec.to_data()
    assert np.abs(r.decoder.residuals[:, 0]).max() > 0  # the canonical knot keeps its residual
    write_recon(tmp_path / "v4.h5", r)
    with h5py.File(tmp_path / "v4.h5") as f:
        assert int(f.attrs["version"]) == 4
    back = read_recon(tmp_path / "v4.h5")
    model, anim = FluidModel.from_recon(back), ParticleAnimation(back)
    assert model.decoder.cfg.canonical_residual
    for t in (0.0, 0.3, 0.5, 1.3, 2.0):  # 0.0 s is the canonical time
        with torch.no_grad():
            ref = model.at(t, with_velocity=True)
        got = anim.at(t, velocity=True)
        np.testing.assert_allclose(got["positions"], ref["means"].numpy(), rtol=0, atol=1e-5, err_msg=f"at {t}")
        np.testing.assert_allclose(got["velocities"], ref["velocities"].numpy(), rtol=0, atol=1e-4, err_msg=f"at {t}")
        np.testing.assert_allclose(got["sh"], ref["sh"].numpy(), rtol=0, atol=1e-5)
    # the canonical frame is the canonical particles moved by their own residual, not A^0 itself
    moved = anim.at(0.0)["positions"] - back.means
    np.testing.assert_allclose(moved, back.decoder.residuals[:, 0, :3], rtol=0, atol=1e-6)
    assert np.abs(anim.at(0.0)["sh"][:, 0] - back.sh[:, 0]).max() > 0.05
    # a file that claims an older version with this encoding is refused, naming the file
    with h5py.File(tmp_path / "v4.h5", "r+") as f:
        f.attrs["version"] = 3
    with pytest.raises(FormatError, match="v4.h5.*canonical_residual.*version 4"):
        read_recon(tmp_path / "v4.h5")
    with pytest.raises(InputError, match="canonical_residual need residuals"):
        DecoderConfig(canonical_residual=True).validate()


def make_recon(n=40, static=False, t=(0.0, 0.5)):
    rng = np.random.default_rng(1)
    dec = None if static else trained_like(n).to_data()
    return ReconData(means=rng.normal(0, 0.1, (n, 3)).astype(np.float32),
                     log_scales=np.full((n, 3), np.log(0.02), np.float32),
                     quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                     logit_opacity=np.zeros(n, np.float32),
                     sh=rng.normal(0, 1, (n, 4, 3)).astype(np.float32), time_min=t[0], time_max=t[1], decoder=dec)


def test_particle_animation_seconds_clamp_and_static(tmp_path):
    write_recon(tmp_path / "r.h5", make_recon())
    r = read_recon(tmp_path / "r.h5")
    anim = ParticleAnimation(r)
    dec = Decoder.from_data(r.decoder)
    a = anim.at(0.25, velocity=True)
    with torch.no_grad():
        ref = dec(0.5, with_velocity=True)
    np.testing.assert_allclose(a["positions"], r.means + ref["dp"].numpy(), atol=1e-5)
    np.testing.assert_allclose(a["velocities"], ref["vp"].numpy() / 0.5, atol=1e-4)
    # outside the clip: clamped to its end with a warning, velocity 0
    with pytest.warns(RuntimeWarning, match="outside the reconstructed clip"):
        late = anim.at(0.9, velocity=True)
    # (to float32 rounding: numpy's matrix products need not repeat bit for bit between calls)
    np.testing.assert_allclose(late["positions"], anim.at(0.5)["positions"], rtol=0, atol=1e-6)
    assert not late["velocities"].any()
    with pytest.raises(InputError, match="outside"):
        ParticleAnimation(r, policy="error").at(-0.1)
    # a static reconstruction has no decoder: its canonical particles at every time
    s = ParticleAnimation(make_recon(static=True))
    np.testing.assert_array_equal(s.at(0.3, velocity=True)["positions"], s.means)
    assert not s.at(0.3, velocity=True)["velocities"].any()
    assert anim.color.shape == (40, 3) and anim.color.min() >= 0 and anim.color.max() <= 1


def test_time_map():
    tm = TimeMap(1.0, 3.0)
    assert tm.tau(2.0) == 0.5 and tm.inside(3.0) and not tm.inside(3.1)
    with pytest.raises(InputError):
        TimeMap(0, 1, policy="wrap")


def test_shared_modules_import_without_torch():
    """What the Blender extension takes from gf_core imports neither torch nor anything that does."""
    code = ("import sys; import gf_core.formats.decoder_np, gf_core.formats.hdf5, gf_core.errors; "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('torch', 'cv2')]; "
            "assert not bad, bad")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
