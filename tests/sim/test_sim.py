"""Simulators: neighbour search, kernels, DFSPH and PBF physics checks, stability suite, CLI."""

import math

import numpy as np
import pytest
import torch

from gf_core.errors import InputError
from gf_core.formats.hdf5 import read_sim
from gf_core.sph.neighbors import knn, neighbor_pairs
from gf_core.sim import (DFSPH, PBF, SCENES, DFSPHParams, initial_state, make_solver, prepare_particles,
                         run_frames, settle, simulate)
from gf_core.sph import kernels
from gf_core.sim.common import Domain, lattice_volume
from gf_core.sim.stability import CASES, run_case, setup_case

G = 9.81


def test_neighbor_pairs_match_brute_force():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(3000, 3, generator=g, dtype=torch.float64)
    y = torch.rand(500, 3, generator=g, dtype=torch.float64) * 1.2 - 0.1
    for a, b in [(x, None), (x, y)]:
        i, j = neighbor_pairs(a, 0.07, b)
        bb = a if b is None else b
        d2 = ((a[:, None] - bb[None]) ** 2).sum(-1)
        mask = d2 < 0.07 ** 2
        if b is None:
            mask.fill_diagonal_(False)
        bi, bj = torch.nonzero(mask, as_tuple=True)
        assert set(zip(i.tolist(), j.tolist())) == set(zip(bi.tolist(), bj.tolist()))
    idx, dist = knn(x, 5, 0.1)
    assert idx.shape == (3000, 5) and torch.all(dist[:, 1:] >= dist[:, :-1])


def test_kernels_normalised_and_gradients_consistent():
    h, d = 0.04, 0.005
    for W in (kernels.cubic, kernels.poly6, kernels.wendland):
        V = lattice_volume(W, h, d)
        assert math.isclose(V, d ** 3, rel_tol=0.02)  # a lattice of spacing d has density 1 / d^3
    r = torch.linspace(0.001, 0.039, 50, dtype=torch.float64)
    dvec = torch.stack([r, torch.zeros_like(r), torch.zeros_like(r)], -1)
    for k in (kernels.CUBIC, kernels.WENDLAND):
        fd = (k.W(r + 1e-7, h) - k.W(r - 1e-7, h)) / 2e-7
        assert torch.allclose(k.grad(dvec, r, h)[:, 0], fd, rtol=1e-5, atol=1e-3), k.name
        assert k.zero(h) == float(k.W(torch.zeros(1, dtype=torch.float64), h))
        assert float(k.W(torch.tensor([h * 1.01]), h)) == 0.0
    # coincident pairs: zero gradient, never NaN
    z = torch.zeros(1, 3, dtype=torch.float64)
    assert torch.equal(kernels.cubic_grad(z, z.norm(dim=-1), h), z)
    assert torch.equal(kernels.wendland_grad(z, z.norm(dim=-1), h), z)
    assert torch.equal(kernels.spiky_grad(z, z.norm(dim=-1), h), z)


@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
def test_lattice_interior_at_rest_density(solver):
    sc, x, v, r = initial_state("hydrostatic_tank", particles=2000)
    s = make_solver(solver, r, sc.domain, sc.material_params)
    m = s.measure(torch.tensor(x), torch.tensor(v))
    assert m["density_err_mean"] < 1e-5 and m["density_err_max"] < 1e-4


def test_dfsph_hydrostatic_tank_stays_at_rest():
    """Targets: mean density error < 0.1 % and max speed < 1 % of sqrt(gH) after 2 s. The
    scene settles for 6 s before t = 0 (``Scene.settle``). Measured over seven settles (seeds
    0-6, run to 5 s; BENCHMARKS.md, "Hydrostatic tank", item 8): density error < 0.01 %, the
    fastest particle at most 0.09-0.50 % over [2, 5] s and at most 0.50 % from 0.8 s on; over the
    whole run 0.23-0.50 %, except one settle (seed 2) that released a 2.8 % bump at 0.3 s; total
    energy never more than 3e-6 J above its start (it falls: the pressure solve is a projection,
    walls included).
    The run to 5 s: ``test_dfsph_hydrostatic_tank_stays_at_rest_to_5s`` (slow)."""
    sim, res = simulate("hydrostatic_tank", solver="dfsph", particles=2000, fps=10, seconds=2.0)
    _assert_tank_at_rest(sim, res)


def _assert_tank_at_rest(sim, res):
    assert sim.config["settle_seconds"] == 6.0
    assert max(s["density_err_mean"] for s in res.steps) < 5e-4
    assert all(s["jacobi_halvings"] == 0 for s in res.steps)  # the safeguard leaves this alone
    ref = math.sqrt(G * 0.2)
    speed = np.linalg.norm(sim.velocities, axis=2).max(axis=1)
    assert speed[0] == 0.0
    assert speed.max() < 0.03 * ref, speed / ref  # a settle can leave a release bump early on
    assert speed[sim.times >= 1.0].max() < 0.01 * ref, speed / ref
    energy = sim.stats["kinetic"] + sim.stats["potential"]
    assert energy.max() - energy[0] < 1e-5, energy - energy[0]  # J; 1e-5 J ~ all moving at 0.1 %
    assert np.all(sim.positions[-1] >= 0) and np.all(sim.positions[-1][:, :2] <= 0.2)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 4])
def test_dfsph_hydrostatic_tank_stays_at_rest_to_5s(seed):
    """The same to 5 s, for two settles (about 4 minutes each on one core). With walls whose
    pressure was extrapolated from the fluid (Adami et al. 2012) the fastest particle grew again
    after 2.5 s, to 2.7 % (seed 0) and 3.2 % (seed 4) at 4 s."""
    sim, res = simulate("hydrostatic_tank", solver="dfsph", particles=2000, fps=10, seconds=5.0,
                        settle_seed=seed)
    _assert_tank_at_rest(sim, res)


def test_settle_brings_a_lattice_to_rest_and_resets_velocities():
    """``settle`` on the tank: the jittered lattice rearranges (speeds of several % of sqrt(gH)
    while damped) and comes out with zero velocity; the warm starts are reset."""
    sc, x, v, r = initial_state("hydrostatic_tank", particles=1000)
    s = make_solver("dfsph", r, sc.domain, sc.material_params)
    xt, vt = torch.tensor(x), torch.tensor(v)
    log = settle(s, xt, vt, seconds=0.5)
    assert log["settle_steps"] > 0 and log["settle_final_speed"] > 0
    assert 0 <= log["settle_density_err_mean"] < 1e-3
    assert float(vt.abs().max()) == 0.0 and s._kappa is None
    jittered, vj = torch.tensor(x), torch.tensor(v)
    assert settle(s, jittered, vj, seconds=0.0)["settle_steps"] == 0  # the jitter alone, same seed
    assert float((jittered - torch.tensor(x)).abs().max()) <= 0.05 * 2 * r + 1e-7
    assert float((xt - jittered).norm(dim=1).max()) > 0.05 * 2 * r  # the damped run moved them on
    with pytest.raises(InputError):
        settle(s, xt, vt, seconds=0.1, damping=1.0)


def test_dfsph_closed_tank_lattice_is_stable():
    """A tank filled to the lid (no free surface), walls continuing the fluid lattice: with the
    Wendland kernel the lattice stays at rest under hydrostatic pressure; with the cubic spline
    the same lattice is unstable and its speed grows ten-fold per 0.1 s up to 7 % by 0.4 s
    (BENCHMARKS.md). Measured with wall pressure unknowns (% of sqrt(gH)): a 0.75 % peak at 0.3 s,
    0.26 % at 0.5 s, 0.08 % at 1 s."""
    sc, x, v, r = initial_state("hydrostatic_tank", particles=2000)
    s = DFSPH(DFSPHParams(particle_radius=r, xsph=0.05), Domain((0, 0, 0), (0.2, 0.2, 0.2)))
    xt, vt = torch.tensor(x), torch.tensor(v)
    res = run_frames(s, xt, vt, fps=10, seconds=0.6, measure_every_step=False)
    speed = np.array([np.linalg.norm(q, axis=1).max() for q in res.velocities]) / math.sqrt(G * 0.2)
    assert speed.max() < 0.015 and speed[-1] < 0.006, speed


# Martin & Moyce (1952), n^2 = 2: surge front Z = x/a against T = t sqrt(2 g / a)
MARTIN_MOYCE = np.array([[0.41, 1.11], [0.84, 1.22], [1.19, 1.44], [1.43, 1.67], [1.63, 1.89],
                         [1.83, 2.11], [1.98, 2.33], [2.20, 2.56], [2.32, 2.78], [2.51, 3.00],
                         [2.65, 3.22], [2.83, 3.44], [2.98, 3.67], [3.11, 3.89]])


@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
def test_dam_break_front_matches_martin_moyce(solver):
    a = 0.2
    sim, _ = simulate("dam_break", solver=solver, particles=2000, fps=50, seconds=0.3)
    T = sim.times * math.sqrt(2 * G / a)
    Z = sim.positions[:, :, 0].max(1) / a
    for k in range(len(T)):
        if 1.4 <= T[k] <= 3.0:
            ref = np.interp(T[k], MARTIN_MOYCE[:, 0], MARTIN_MOYCE[:, 1])
            # SPH codes run 0-20 % ahead of the experiment (the gate took time to lift)
            assert 0.9 <= Z[k] / ref <= 1.3, (solver, T[k], Z[k], ref)


def test_falling_sphere_energy_does_not_grow():
    sim, _ = simulate("water_sphere", solver="dfsph", particles=1500, fps=20, seconds=0.6)
    e = sim.stats["kinetic"] + sim.stats["potential"]
    assert np.all(e <= e[0] * 1.01 + 1e-9), e
    assert e[-1] < e[0]  # the splash dissipates


def test_honey_is_more_viscous_than_water():
    """Same cone, water vs honey: honey spreads less in the same time (implicit viscosity).
    Measured, farthest particle at 0.6 s: honey 0.28 m, water 0.55 m."""
    def spread(material_override):
        sc, x, v, r = initial_state("honey_cone", particles=1200)
        params = dict(sc.material_params, **material_override)
        s = make_solver("dfsph", r, sc.domain, params)
        xt, vt = torch.tensor(x), torch.tensor(v)
        res = run_frames(s, xt, vt, fps=10, seconds=0.6)
        assert all(s_["viscosity_iterations"] < 50 for s_ in res.steps)  # no sub-stepping needed
        return float(xt[:, :2].norm(dim=-1).max())
    water = spread({"viscosity": 0.0, "xsph": 0.05, "rest_density": 1000.0})
    honey = spread({})
    assert honey < 0.8 * water, (honey, water)


def test_pbf_from_arbitrary_positions_estimates_rest_state():
    sc, x, v, r = initial_state("water_cube", particles=1500)
    s = PBF.from_positions(x, sc.domain)
    lattice = make_solver("pbf", r, sc.domain, sc.material_params)
    assert math.isclose(s.p.particle_radius, r, rel_tol=0.01)
    assert math.isclose(s.V, lattice.V, rel_tol=0.03)
    rng = np.random.default_rng(0)
    xj = x + rng.normal(scale=0.1 * r, size=x.shape).astype(np.float32)  # a "reconstruction"
    s = PBF.from_positions(xj, sc.domain)
    xt, vt = torch.tensor(xj), torch.zeros(xj.shape)
    run_frames(s, xt, vt, fps=10, seconds=0.3)
    assert torch.isfinite(xt).all() and float(xt[:, 2].min()) >= 0.0
    with pytest.raises(InputError, match="need"):
        PBF.from_positions(np.zeros((1, 3)), sc.domain)


def test_rest_state_of_a_disordered_set_puts_a_resting_fluid_at_rest_density():
    """A reconstruction is no lattice: its nearest-neighbour distances sit below its mean spacing.
    The estimated rest state (spacing from the rest volume, not from the nearest neighbour) lays
    the walls at the fluid's own density: a jittered tank of water at rest starts as little
    compressed as with the true lattice parameters; with walls at the nearest-neighbour spacing
    (the first guess, ``iterations=0``) it started 10x more compressed and was thrown off the floor."""
    from gf_core.sim import DFSPH, DFSPHParams
    from gf_core.sim.common import estimate_rest_state
    from gf_core.sph import kernels

    sc, x, v, r = initial_state("hydrostatic_tank", particles=1000)
    xj = (x + np.random.default_rng(0).normal(scale=0.1 * r, size=x.shape)).astype(np.float32)
    sp_nn, V_nn = estimate_rest_state(xj, kernels.WENDLAND.W, iterations=0)
    solvers = {"lattice": make_solver("dfsph", r, sc.domain, sc.material_params),
               "estimated": DFSPH.from_positions(xj, sc.domain),
               "nearest": DFSPH(DFSPHParams(particle_radius=sp_nn / 2, rest_volume=V_nn), sc.domain)}
    assert math.isclose(solvers["estimated"].spacing, 2 * r, rel_tol=0.03)
    err = {k: s.measure(torch.tensor(xj), torch.zeros(xj.shape))["density_err_mean"] for k, s in solvers.items()}
    assert err["estimated"] < 1.2 * err["lattice"] and err["nearest"] > 5 * err["estimated"], err


def test_dfsph_jacobi_backs_off_instead_of_diverging():
    """Half a dam-break column mirrored into the box crushes particles together (densities up to
    18x rest): plain Jacobi grew the error 20-fold per iteration to NaN in the first step. The
    solve now halves its relaxation after an update that more than doubles the error."""
    sc, x, v, r, _ = setup_case("outside_box", "dfsph", 400)
    s = make_solver("dfsph", r, sc.domain, sc.material_params)
    x, v, _ = prepare_particles(x, v, sc.domain, 2 * r)
    xt, vt = torch.tensor(x, dtype=torch.float32), torch.tensor(v, dtype=torch.float32)
    before = s.measure(xt, vt)["density_err_mean"]
    info = s.step(xt, vt, 0.005)
    assert info["jacobi_halvings"] > 0
    assert torch.isfinite(xt).all() and torch.isfinite(vt).all()
    assert s.measure(xt, vt)["density_err_mean"] < 0.8 * before  # 8.2 -> 5.6; the run: test_stability_suite


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
def test_stability_suite(case, solver):
    r = run_case(case, solver, particles=400, seconds=0.2)
    assert r["ok"], r
    if case == "zero_particles":
        assert "no particles" in r["refused"]
    else:
        assert r["finite"] and r["inside"] and r["max_speed_rel"] < 3.5
    if case in ("hydrostatic", "large_dt_at_rest"):
        # water at rest stays near rest even with a 10x step cap: without the force limit on dt
        # DFSPH reached 0.90 sqrt(gH) and PBF 1.0 sqrt(gH) here; with it 0.02 and 0.17 (PBF at
        # 4 iterations is compressible and bounces 0.25 sqrt(gH) at its default step too)
        assert r["max_speed_rel"] < (0.1 if solver == "dfsph" else 0.4), r
    if case == "coincident":
        assert r["coincident_separated"] > 0
    if case == "outside_box":
        # particles pushed back into the box must not collapse onto one face line: coincident
        # particles have no pressure gradient (with clamping instead of mirroring, DFSPH kept a
        # 9 % mean density error from such clusters)
        assert r["density_err_mean"] < 0.02, r
        assert r["outside_moved"] > 0


def test_bad_parameters_refused_up_front():
    dom = Domain((0, 0, 0), (1, 1, 1))
    with pytest.raises(InputError, match="cfl 4.0 > 1"):
        make_solver("dfsph", 0.01, dom, {"cfl": 4.0})
    with pytest.raises(InputError, match="particle_radius must be a positive"):
        make_solver("pbf", float("nan"), dom, {})
    with pytest.raises(InputError, match="unknown solver 'sph'"):
        make_solver("sph", 0.01, dom, {})
    with pytest.raises(InputError, match="must exceed min"):
        Domain((0, 0, 0), (1, 0, 1))
    with pytest.raises(InputError, match="unknown scene"):
        simulate("lava_lamp")


def test_simulate_cli_writes_sim_h5(tmp_path):
    from gf_cli.main import main

    out = tmp_path / "sim.h5"
    assert main(["simulate", "water_cube", "--out", str(out), "--particles", "300", "--seconds", "0.1",
                 "--fps", "30", "--quiet"]) == 0
    sim = read_sim(out)
    assert sim.num_frames == 4 and sim.solver == "dfsph" and sim.scene == "water_cube"
    assert sim.stats["density_err_mean"].shape == (4,)
    assert not np.allclose(sim.positions[0], sim.positions[-1])  # it fell
    assert set(SCENES) >= {"water_cube", "water_sphere", "honey_cone", "dam_break", "hydrostatic_tank"}


def test_simulate_cli_settle_option(tmp_path):
    """--settle overrides the scene's settling time; the run starts at rest from the settled state."""
    from gf_cli.main import main

    out = tmp_path / "tank.h5"
    assert main(["simulate", "hydrostatic_tank", "--out", str(out), "--particles", "300", "--seconds", "0.1",
                 "--fps", "10", "--settle", "0.2", "--quiet"]) == 0
    sim = read_sim(out)
    assert sim.config["settle_seconds"] == 0.2 and sim.config["settle_steps"] > 0
    assert np.abs(sim.velocities[0]).max() == 0.0
    lattice = initial_state("hydrostatic_tank", particles=300)[1]
    assert np.abs(sim.positions[0] - lattice).max() > 0.01 * 2 * sim.particle_radius


@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
def test_viscosity_boundary_free_slip_keeps_sliding_no_slip_brakes(solver):
    """A slab of viscous fluid sliding along the floor: with free-slip walls (the default) the
    viscosity only shears the fluid internally, so a uniform slide keeps its speed; no-slip walls
    brake the particles next to the floor."""
    domain = Domain((0.0, 0.0, 0.0), (1.0, 0.4, 0.3))
    s = 0.02
    ax = [np.arange(0.2, 0.8, s) + s / 2, np.arange(0.0, 0.4, s) + s / 2, np.arange(0.0, 0.08, s) + s / 2]
    x0 = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    speed = {}
    for boundary in ("free-slip", "no-slip"):
        sol = make_solver(solver, s / 2, domain, {"rest_density": 1000.0, "viscosity": 0.05, "xsph": 0.0},
                          viscosity_boundary=boundary)
        x = torch.tensor(x0, dtype=torch.float32)
        v = torch.zeros_like(x)
        v[:, 0] = 0.5
        t = 0.0
        while t < 0.05 - 1e-9:
            t += sol.step(x, v, 0.05 - t)["dt"]
        speed[boundary] = float(v[:, 0].mean())
    assert speed["free-slip"] > 0.45, speed
    assert speed["no-slip"] < 0.8 * speed["free-slip"], speed
    with pytest.raises(InputError, match="viscosity_boundary"):
        make_solver(solver, s / 2, domain, {"rest_density": 1000.0}, viscosity_boundary="sticky")


@pytest.mark.parametrize("solver", ["dfsph", "pbf"])
def test_an_interrupted_simulation_resumes_only_with_the_same_settings(solver, tmp_path):
    """simulate(out=...) interrupted at frame 6 goes on from there when called again the same
    way (exactly the uninterrupted frames); with other settings it starts afresh."""
    from gf_core.formats.hdf5 import read_sim
    from gf_core.sim import simulate

    def stop_at_6(f, n, t, last):
        if f == 6:
            raise KeyboardInterrupt

    import h5py

    kw = dict(particles=300, fps=20, seconds=0.6, solver=solver)
    full, _ = simulate("water_cube", out=tmp_path / "full.h5", **kw)
    with pytest.raises(KeyboardInterrupt):
        simulate("water_cube", out=tmp_path / "s.h5", progress=stop_at_6, **kw)
    part = read_sim(tmp_path / "s.h5")
    assert not part.complete and part.num_frames == 7
    sim, _ = simulate("water_cube", out=tmp_path / "s.h5", **kw)
    assert sim.config["resumed_after_frame"] == 6 and sim.complete
    assert np.array_equal(sim.positions, full.positions) and np.array_equal(sim.velocities, full.velocities)
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert "resume_state" not in f  # dropped once complete

    with pytest.raises(KeyboardInterrupt):
        simulate("water_cube", out=tmp_path / "s.h5", progress=stop_at_6, **kw)
    other, _ = simulate("water_cube", out=tmp_path / "s.h5", **{**kw, "seconds": 0.5})
    assert "resumed_after_frame" not in other.config and other.num_frames == 11 and read_sim(tmp_path / "s.h5").complete
