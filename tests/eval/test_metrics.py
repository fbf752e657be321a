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


def _brute_field(mu, s, qn, o, pts):
    """sum_i o_i exp(-1/2 d^T Sigma_i^-1 d) at ``pts``, every particle, with scipy's rotation."""
    from scipy.spatial.transform import Rotation

    out = np.zeros(len(pts))
    for i in range(len(mu)):
        R = Rotation.from_quat(qn[i, [1, 2, 3, 0]]).as_matrix()
        cov = R @ np.diag(s[i] ** 2) @ R.T
        d = pts - mu[i]
        out += o[i] * np.exp(-0.5 * np.einsum("mi,ij,mj->m", d, np.linalg.inv(cov), d))
    return out


def test_gaussian_cell_means_are_the_fields_averages_over_the_cells():
    from gf_core.eval.metrics import gaussian_cell_mean

    rng = np.random.default_rng(0)
    lo, cell, shape = np.array([-0.5, -0.5, 0.0]), np.array([0.1, 0.1, 0.125]), (10, 10, 8)
    n = 12
    mu = rng.uniform([-0.15, -0.15, 0.35], [0.15, 0.15, 0.65], (n, 3))  # 3.5 sigma inside the grid
    o = rng.uniform(0.1, 1, n)
    sub = 12  # brute force: the field at sub^3 points per cell, averaged
    u = (np.arange(sub) + 0.5) / sub - 0.5
    off = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3) * cell
    axes = [lo[a] + (np.arange(shape[a]) + 0.5) * cell[a] for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    for case, s, q in (("isotropic, smaller than a cell", np.repeat(rng.uniform(0.02, 0.05, (n, 1)), 3, 1),
                        rng.normal(size=(n, 4))),
                       ("axis-aligned, anisotropic", rng.uniform(0.02, 0.08, (n, 3)), np.tile([1.0, 0, 0, 0], (n, 1))),
                       ("rotated, anisotropic", rng.uniform(0.03, 0.08, (n, 3)), rng.normal(size=(n, 4)))):
        qn = q / np.linalg.norm(q, axis=1, keepdims=True)
        want = np.mean([_brute_field(mu, s, qn, o, centres + d) for d in off], 0).reshape(shape)
        got = gaussian_cell_mean(mu, s, q, o, lo, cell, shape, k=n)
        assert got.shape == shape
        err = np.abs(got - want).max() / want.max()
        assert err < (0.02 if case.startswith("rotated") else 5e-3), (case, err)  # the brute force's own error ~0.3 %
        if case.startswith("rotated"):
            assert np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.995
        # nothing is lost: the cells hold every Gaussian's integral o (2 pi)^(3/2) s1 s2 s3
        total = (o * (2 * np.pi) ** 1.5 * s.prod(1)).sum()
        assert abs(got.sum() * cell.prod() - total) < 1e-3 * total
    # a rotated needle about a cell long, its k nearest cells up to 0.7 m away (a plume's grid): far
    # along the needle the correction's exponent would overflow; the means stay finite, all counted
    c2, shape2 = np.full(3, 0.0125), (32, 32, 48)
    q45 = np.array([[np.cos(np.pi / 8), np.sin(np.pi / 8), 0.0, 0.0]] * 2)   # 45 degrees about x
    s2 = np.array([[0.001, 0.001, 0.010]] * 2)
    got = gaussian_cell_mean(np.array([[0.0, 0.15, 0.05], [0.0, -0.15, 0.55]]), s2, q45, [1.0, 1.0],
                             [-0.2, -0.2, 0.0], c2, shape2, k=2)
    assert np.isfinite(got).all() and got.min() >= 0
    total = 2 * (2 * np.pi) ** 1.5 * s2[0].prod()
    assert abs(got.sum() * c2.prod() - total) < 0.1 * total  # a 10:1 needle: the approximation's worst case
    # a Gaussian much smaller than a cell, off the cell centres: all of it is counted
    s = np.full((1, 3), 0.015)
    one = gaussian_cell_mean(np.array([[0.04, 0.04, 0.5]]), s, np.array([[1.0, 0, 0, 0]]), [1.0], lo, cell, shape)
    assert abs(one.sum() * cell.prod() - (2 * np.pi) ** 1.5 * 0.015 ** 3) < 1e-9


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


def test_flow_error_tells_particles_moving_with_the_flow_from_ones_standing_in_it():
    """metrics.flow_error: the true flow at each reconstructed particle is its nearest true
    particle's velocity. Reconstructed particles on a shear flow that move with it follow 1 of it
    with no error; standing still they follow 0 with the flow's mean speed as error; moving twice
    as fast, 2; empty sets give NaN, not an exception."""
    from gf_core.eval.metrics import flow_error

    rng = np.random.default_rng(0)
    gt = rng.uniform(0, 1, (2000, 3))
    vel = np.stack([gt[:, 2], np.zeros(len(gt)), np.zeros(len(gt))], 1) * 2.0   # u = 2 z
    rec = gt[rng.permutation(len(gt))[:500]] + rng.normal(0, 1e-4, (500, 3))
    with_flow = flow_error(rec, with_flow_v(rec), gt, vel)
    assert with_flow["flow_following"] == pytest.approx(1.0, abs=0.01)
    assert with_flow["velocity_error"] < 0.02
    still = flow_error(rec, np.zeros_like(rec), gt, vel)
    assert still["flow_following"] == 0.0
    assert still["velocity_error"] == pytest.approx(np.abs(2 * rec[:, 2]).mean(), rel=0.01)
    assert still["true_speed"] == pytest.approx(np.sqrt(((2 * rec[:, 2]) ** 2).mean()), rel=0.01)
    assert flow_error(rec, 2 * with_flow_v(rec), gt, vel)["flow_following"] == pytest.approx(2.0, abs=0.02)
    assert np.isnan(flow_error(np.zeros((0, 3)), np.zeros((0, 3)), gt, vel)["flow_following"])


def with_flow_v(x):
    return np.stack([x[:, 2] * 2.0, 0 * x[:, 0], 0 * x[:, 0]], 1)
