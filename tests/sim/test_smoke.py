"""The smoke plume on a grid (stable fluids): it rises, its velocity is made divergence-free, it is
seeded and deterministic, and large frame intervals stay stable."""

import numpy as np
import pytest
import torch

from gf_core.errors import InputError
from gf_core.sim.smoke import PlumeConfig, _div, _project, _walls, simulate_plume


def centroid_z(d, cell):
    z = (np.arange(d.shape[2]) + 0.5) * cell[2]
    return float((d.sum((0, 1)) * z).sum() / d.sum())


def test_the_plume_rises_and_spreads():
    g = simulate_plume(PlumeConfig(cells=24, seconds=1.0, fps=10))
    assert g.density.shape == (11, 16, 16, 24) and np.all(np.isfinite(g.density)) and g.density.min() >= 0
    assert g.density[0].sum() == 0
    heights = [centroid_z(g.density[f], g.cell) for f in range(1, 11)]
    assert heights[-1] > heights[0] + 0.05          # the smoke's centre climbs
    top = [np.nonzero(g.density[f].sum((0, 1)) > 1e-3)[0].max() for f in (2, 10)]
    assert top[1] > top[0] + 4                      # its front climbs by more than 4 cells
    mass = g.density.sum((1, 2, 3))
    assert np.all(np.diff(mass[1:]) > 0)            # the source keeps adding smoke


def test_seeded_and_deterministic():
    a, b = (simulate_plume(PlumeConfig(cells=12, seconds=0.4, fps=10, seed=s)) for s in (1, 1))
    c = simulate_plume(PlumeConfig(cells=12, seconds=0.4, fps=10, seed=2))
    assert np.array_equal(a.density, b.density) and not np.array_equal(a.density, c.density)


def test_projection_removes_the_divergence():
    gen = torch.Generator().manual_seed(0)
    v = _walls(torch.randn((3, 14, 12, 16), generator=gen, dtype=torch.float64))
    h = 0.01
    w = _project(v, h, 600)
    assert _div(w, h).abs().max() < 1e-6 * _div(v, h).abs().max()
    assert torch.equal(w, _walls(w))                               # nothing flows through the walls
    assert torch.allclose(_project(w, h, 600), w, atol=1e-5)       # a projection: divergence-free stays put


def test_large_frame_interval_is_sub_stepped_and_finite():
    g = simulate_plume(PlumeConfig(cells=16, seconds=2.0, fps=2, buoyancy=20.0))
    assert np.all(np.isfinite(g.density)) and g.density[-1].sum() > 0


@pytest.mark.parametrize("kw", [dict(cells=4), dict(fps=0.0), dict(seconds=float("nan")), dict(domain=(0.4, 0.0, 1.0))])
def test_bad_settings_are_refused(kw):
    with pytest.raises(InputError):
        simulate_plume(PlumeConfig(**kw))
