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
