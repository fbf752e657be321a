"""Measures of a reconstruction beyond the images: the shape spread of Eqs. 7-8 and the volume the
particles fill."""


import numpy as np
import pytest
import torch



def test_shape_spread_reports_eqs_7_and_8_and_axis_ratios():
    from gf_core.eval.metrics import shape_spread

    s = shape_spread(torch.tensor([[1.0, 1.0, 1.0], [1.0, 2.0, 4.0]]))
    assert s["volume"] == pytest.approx(((1 / 4.5 - 1) ** 2 + (8 / 4.5 - 1) ** 2) / 2)
    assert s["aniso"] == pytest.approx((0.25 + 0 + 1) / 2)
    assert s["axis_ratio_median"] == 1.0 and s["axis_ratio_p95"] == pytest.approx(1 + 0.95 * 3)
    assert shape_spread(torch.full((5, 3), 0.01))["aniso"] == pytest.approx(0.0, abs=1e-12)


def test_particle_volume_is_the_volume_a_packed_block_fills():
    """metrics.particle_volume: N / the median SPH number density; a jittered lattice block of
    12^3 particles at 1 cm fills 12^3 cm^3 (each particle its cell); several frames average; no
    particles is an error."""
    from gf_core.eval.metrics import particle_volume

    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.01
    x = g + np.random.default_rng(0).normal(0, 0.001, g.shape)
    true = len(g) * 0.01 ** 3
    assert particle_volume([x], 0.025) == pytest.approx(true, rel=0.06)
    assert particle_volume([x, 2 * x], 0.05) == pytest.approx(4.5 * true, rel=0.1)  # 1x and 8x the block
    with pytest.raises(ValueError, match="no particles"):
        particle_volume([np.zeros((0, 3))], 0.025)


def test_gaussian_density_matches_the_sum_of_the_gaussians():
    from gf_core.eval.metrics import gaussian_density

    rng = np.random.default_rng(0)
    mu = rng.uniform(-1, 1, (20, 3))
    s = rng.uniform(0.05, 0.3, (20, 3))
    q = rng.normal(size=(20, 4))
    o = rng.uniform(0.1, 1, 20)
    pts = rng.uniform(-1, 1, (50, 3))
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    want = np.zeros(50)
    for i in range(20):  # brute force, every particle, with scipy's rotation
        from scipy.spatial.transform import Rotation

        R = Rotation.from_quat(qn[i, [1, 2, 3, 0]]).as_matrix()
        cov = R @ np.diag(s[i] ** 2) @ R.T
        d = pts - mu[i]
        want += o[i] * np.exp(-0.5 * np.einsum("mi,ij,mj->m", d, np.linalg.inv(cov), d))
    got = gaussian_density(mu, s, q, o, pts, k=20)
    assert np.allclose(got, want, rtol=1e-9, atol=1e-12)


def test_density_agreement_scores_the_same_field_one_and_a_shuffled_one_near_zero():
    from gf_core.eval.metrics import density_agreement

    rng = np.random.default_rng(1)
    truth = [rng.gamma(2.0, 1.0, (8, 8, 8)) for _ in range(3)]
    same = density_agreement([2.5 * t for t in truth], truth)
    assert abs(same["scale"] - 0.4) < 1e-12 and same["corr_min_frame"] > 0.999999 and same["error_mean"] < 1e-9
    shuffled = density_agreement([rng.permutation(t.ravel()) for t in truth], truth)
    assert abs(shuffled["corr_mean"]) < 0.15 and shuffled["error_mean"] > 0.3
    with_empty = density_agreement([truth[0], np.ones((8, 8, 8))] , [truth[0], np.zeros((8, 8, 8))])
    assert with_empty["per_frame"][1]["empty_truth"] and with_empty["corr_min_frame"] > 0.999999
