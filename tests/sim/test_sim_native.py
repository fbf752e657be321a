"""The native SPH engine (csrc/sim_cpu.cpp) against the torch reference: neighbour lists, kernel
sums, and DFSPH's neighbourhood, Jacobi solves and whole steps."""

import math

import numpy as np
import pytest
import torch

from gf_core.sph.neighbors import build_grid, neighbor_lists, neighbor_pairs, neighbor_pairs_torch
from gf_core import native
from gf_core.sim import initial_state, make_solver, simulate
from gf_core.sph import kernels
from gf_core.sim.common import Measure


@pytest.fixture(scope="module", autouse=True)
def built():
    assert native.available(), native.unavailable_reason()


def pair_set(i, j):
    return set(zip(i.tolist(), j.tolist()))


CASES = {
    "random": lambda g: torch.rand(1500, 3, generator=g, dtype=torch.float64),
    "lattice": lambda g: torch.stack(torch.meshgrid(*[torch.arange(9.0, dtype=torch.float64)] * 3, indexing="ij"),
                                     -1).reshape(-1, 3) * 0.1,
    "empty": lambda g: torch.zeros(0, 3, dtype=torch.float64),
    "one": lambda g: torch.rand(1, 3, generator=g, dtype=torch.float64),
    "coincident": lambda g: torch.cat([torch.zeros(6, 3, dtype=torch.float64),
                                       torch.rand(80, 3, generator=g, dtype=torch.float64)]),
    "far_outside": lambda g: torch.cat([torch.rand(300, 3, generator=g, dtype=torch.float64),
                                        torch.tensor([[1e5, -3e4, 7e3], [1e14, 0.0, 0.0], [1e14, 0.0, 0.05]],
                                                     dtype=torch.float64)]),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_neighbor_lists_match_the_torch_grid_and_brute_force(case, dtype):
    g = torch.Generator().manual_seed(7)
    x = CASES[case](g).to(dtype)
    r = 0.101  # the lattice spacing is 0.1: every lattice neighbour sits just inside
    i, j = neighbor_pairs(x, r, backend="native")
    ti, tj = neighbor_pairs_torch(x, r)
    assert pair_set(i, j) == pair_set(ti, tj)
    if x.shape[0]:
        d = torch.cdist(x.double(), x.double())
        mask = (d < r) & ~torch.eye(x.shape[0], dtype=torch.bool)
        if case != "far_outside":  # cdist loses the 0.05 gap at 1e14; the grids keep it (exact differences)
            assert pair_set(i, j) == pair_set(*torch.nonzero(mask, as_tuple=True))
    rowptr, col = neighbor_lists(x, r)
    assert rowptr.shape == (x.shape[0] + 1,) and rowptr[-1] == col.numel()
    assert torch.equal(torch.diff(rowptr) >= 0, torch.ones(x.shape[0], dtype=torch.bool))
    for a in range(x.shape[0]):  # ascending within each row
        row = col[rowptr[a]:rowptr[a + 1]]
        assert torch.all(row[1:] > row[:-1])
    if case == "far_outside" and dtype == torch.float64:
        assert (x.shape[0] - 2, x.shape[0] - 1) in pair_set(i, j)  # 0.05 apart at 1e14 m


def test_neighbor_lists_between_sets_with_a_grid_built_once():
    g = torch.Generator().manual_seed(8)
    walls = torch.rand(2000, 3, generator=g) * 2 - 0.5
    grid = build_grid(walls, 0.12)
    for k in range(3):  # the same grid serves moving queries
        x = torch.rand(700, 3, generator=g) + 0.1 * k
        rowptr, col = neighbor_lists(x, 0.12, walls, grid=grid)
        i = torch.repeat_interleave(torch.arange(700), torch.diff(rowptr))
        assert pair_set(i, col) == pair_set(*neighbor_pairs_torch(x, 0.12, walls))
    with pytest.raises(RuntimeError, match="cell size must equal"):
        neighbor_lists(x, 0.2, walls, grid=grid)
    with pytest.raises(RuntimeError, match="not built over y"):
        neighbor_lists(x, 0.12, walls[:10], grid=grid)


def test_neighbor_lists_refuse_bad_input():
    x = torch.rand(20, 3)
    x[4, 2] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        neighbor_pairs(x, 0.3, backend="native")
    with pytest.raises(RuntimeError, match="NaN"):
        neighbor_lists(x, 0.3)
    with pytest.raises(ValueError, match="unknown neighbour backend"):
        neighbor_pairs(torch.rand(5, 3), 0.3, backend="fast")
    y = torch.rand(20, 3)
    with pytest.raises(RuntimeError, match="same tensor"):  # "leave i out of its own row" needs x to be y
        native.load().radius_pairs(y, y.clone(), [], 0.3, True)
    nc = torch.rand(3, 20).t()  # not contiguous: still searched among itself
    rowptr, col = neighbor_lists(nc, 0.3)
    assert pair_set(*neighbor_pairs_torch(nc, 0.3)) == pair_set(
        torch.repeat_interleave(torch.arange(20), torch.diff(rowptr)), col)


@pytest.mark.parametrize("kernel", [kernels.CUBIC, kernels.WENDLAND])
def test_native_measure_matches_the_torch_measure(kernel, monkeypatch):
    sc, x, v, r = initial_state("dam_break", particles=1500)
    s = make_solver("dfsph", r, sc.domain, sc.material_params)
    g = torch.Generator().manual_seed(1)
    xt = torch.tensor(x, dtype=torch.float64) + 0.2 * r * torch.randn(x.shape, generator=g, dtype=torch.float64)
    m = Measure(h=s.h, V=s.V, wall=s.wall.double(), gravity=s.g.double(), z0=0.0, mass=1.0, kernel=kernel)
    a = m.density(xt)
    monkeypatch.setattr("gf_core.sim.common.native_available", lambda: False)
    b = m.density(xt)
    assert torch.allclose(a, b, rtol=1e-12, atol=0)


def dam_break_state(n=1500, seed=0):
    sc, x, v, r = initial_state("dam_break", particles=n)
    g = torch.Generator().manual_seed(seed)
    xt = torch.tensor(x, dtype=torch.float32)
    xt += 0.3 * r * torch.randn(xt.shape, generator=g)
    vt = 0.3 * torch.randn(xt.shape, generator=g)
    return sc, xt, vt, r


def test_dfsph_native_neighbourhood_and_step_match_torch():
    """The same state through both paths: densities, factors and counts equal to round-off, and
    after one step (XSPH, both Jacobi solves, advection) velocities and positions agree."""
    sc, x, v, r = dam_break_state()
    sn = make_solver("dfsph", r, sc.domain, sc.material_params, backend="native")
    st = make_solver("dfsph", r, sc.domain, sc.material_params, backend="torch")
    assert sn.native and not st.native
    a, b = sn._neighbourhood(x), st._neighbourhood(x)
    assert torch.equal(a["count"], b["count"])
    assert torch.allclose(a["rho_all"], b["rho_all"], rtol=1e-5)
    assert torch.allclose(a["alpha"], b["alpha"], rtol=1e-4)
    xn, vn, xt_, vt_ = x.clone(), v.clone(), x.clone(), v.clone()
    for _ in range(3):
        inf_n = sn.step(xn, vn, 0.01)
        inf_t = st.step(xt_, vt_, 0.01)
        assert inf_n["dt"] == pytest.approx(inf_t["dt"], rel=1e-5)
        assert abs(inf_n["iterations"] - inf_t["iterations"]) <= 1
    rel = float((vn - vt_).norm() / vt_.norm())
    assert rel < 1e-4, rel
    assert float((xn - xt_).abs().max()) < 1e-4 * r


def test_dfsph_native_runs_like_torch_in_a_dam_break():
    """0.15 s of dam break on both paths: the same steps and iteration counts, the same front and
    density error (the paths part by round-off, which a breaking dam amplifies)."""
    out = {}
    for be in ("native", "torch"):
        sim, res = simulate("dam_break", solver="dfsph", particles=800, fps=40, seconds=0.15, settle_seconds=0,
                            backend=be)
        out[be] = (sim, res)
    (sn, rn), (st, rt) = out["native"], out["torch"]
    assert abs(len(rn.steps) - len(rt.steps)) <= 1
    it_n = np.mean([s["iterations"] for s in rn.steps])
    it_t = np.mean([s["iterations"] for s in rt.steps])
    assert it_n == pytest.approx(it_t, rel=0.05)
    front_n, front_t = sn.positions[-1][:, 0].max(), st.positions[-1][:, 0].max()
    assert abs(front_n - front_t) < 0.5 * 2 * sn.particle_radius
    assert np.mean(sn.stats["density_err_mean"]) == pytest.approx(np.mean(st.stats["density_err_mean"]), rel=0.1)
    assert sn.config["backend"] == "native"


def test_dfsph_backend_option_checked():
    sc, x, v, r = initial_state("dam_break", particles=200)
    from gf_core.errors import InputError

    with pytest.raises(InputError, match="unknown backend"):
        make_solver("dfsph", r, sc.domain, sc.material_params, backend="fast")
    if torch.cuda.is_available():  # pragma: no cover - GPU machines only
        with pytest.raises(InputError, match="CPU tensors"):
            make_solver("dfsph", r, sc.domain, sc.material_params, backend="native", device="cuda")
    assert math.isfinite(make_solver("dfsph", r, sc.domain, sc.material_params, backend="torch").V)


def test_pbf_native_iterations_match_torch():
    """PBF's constraint iterations, native against torch: one substep from the same state, then a
    short dam break with the same front and density error."""
    sc, x, v, r = dam_break_state(seed=2)
    sn = make_solver("pbf", r, sc.domain, sc.material_params, backend="native")
    st = make_solver("pbf", r, sc.domain, sc.material_params, backend="torch")
    assert sn.native and not st.native
    xn, vn, xt_, vt_ = x.clone(), v.clone(), x.clone(), v.clone()
    a, b = sn.step(xn, vn, 0.01), st.step(xt_, vt_, 0.01)
    assert a["dt"] == b["dt"]
    assert a["density_residual"] == pytest.approx(b["density_residual"], rel=1e-4)
    assert float((xn - xt_).abs().max()) < 1e-5 * r
    assert float((vn - vt_).norm() / vt_.norm()) < 1e-4
    out = {}
    for be in ("native", "torch"):
        out[be], _ = simulate("dam_break", solver="pbf", particles=800, fps=40, seconds=0.15, settle_seconds=0,
                              backend=be)
    fn, ft = out["native"].positions[-1][:, 0].max(), out["torch"].positions[-1][:, 0].max()
    assert abs(fn - ft) < 0.5 * 2 * r
    assert np.mean(out["native"].stats["density_err_mean"]) == pytest.approx(
        np.mean(out["torch"].stats["density_err_mean"]), rel=0.1)


@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
@pytest.mark.parametrize("boundary", ["free-slip", "no-slip"])
def test_native_viscosity_operator_matches_torch(solver, boundary):
    """The implicit viscosity (conjugate gradients on (I - nu dt L) v = v*) with the operator
    applied natively against the torch pair sums: one step of a viscous fluid from the same state."""
    sc, x, v, r = dam_break_state(seed=4)
    mat = dict(sc.material_params, viscosity=0.05, viscosity_boundary=boundary)
    sn = make_solver(solver, r, sc.domain, mat, backend="native")
    st = make_solver(solver, r, sc.domain, mat, backend="torch")
    xn, vn, xt_, vt_ = x.clone(), v.clone(), x.clone(), v.clone()
    a, b = sn.step(xn, vn, 0.005), st.step(xt_, vt_, 0.005)
    assert a["viscosity_iterations"] > 0
    assert abs(a["viscosity_iterations"] - b["viscosity_iterations"]) <= 1
    assert float((vn - vt_).norm() / vt_.norm()) < 1e-4
