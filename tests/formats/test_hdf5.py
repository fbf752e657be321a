import h5py
import numpy as np
import pytest

from gf_core.errors import FormatError, InputError
from gf_core.formats.hdf5 import (DecoderData, ReconData, SimData, read_recon, read_sim, write_recon,
                        write_sim)


def make_sim(rng, frames=4, n=50):
    pos = rng.uniform(0, 1, (frames, n, 3)).astype(np.float32)
    return SimData(positions=pos, velocities=np.zeros_like(pos), fps=60.0, particle_radius=0.01,
                   rest_density=1000.0, viscosity=0.01, solver="dfsph", scene="water_cube",
                   config={"spacing": 0.02}, stats={"density_error_mean": np.zeros(frames)})


def make_recon(rng, n=30, dynamic=True):
    dec = None
    if dynamic:
        dec = DecoderData(features=rng.normal(size=(n, 8)).astype(np.float32),
                          layers=[(rng.normal(size=(16, 8 + 9)), rng.normal(size=16)),
                                  (rng.normal(size=(10, 16)), rng.normal(size=10))],
                          encoding={"n_freqs": 4, "include_input": True},
                          outputs={"dp": 3, "ds": 3, "dr": 4})
    return ReconData(means=rng.normal(size=(n, 3)), log_scales=rng.normal(size=(n, 3)) - 4,
                     quats=rng.normal(size=(n, 4)), logit_opacity=rng.normal(size=n),
                     sh=rng.normal(size=(n, 4, 3)), time_min=0.0, time_max=1.0, decoder=dec,
                     config={"lr": 0.01}, metrics={"psnr": 30.0})


def test_sim_round_trip(tmp_path, rng):
    sim = make_sim(rng)
    write_sim(tmp_path / "sim.h5", sim)
    back = read_sim(tmp_path / "sim.h5")
    assert np.array_equal(back.positions, sim.positions)
    assert np.allclose(back.times, np.arange(4) / 60.0)
    assert back.solver == "dfsph" and back.scene == "water_cube" and back.config == {"spacing": 0.02}
    assert back.gravity == (0.0, 0.0, -9.81)
    assert "density_error_mean" in back.stats


@pytest.mark.parametrize("dynamic", [True, False])
def test_recon_round_trip(tmp_path, rng, dynamic):
    r = make_recon(rng, dynamic=dynamic)
    write_recon(tmp_path / "recon.h5", r)
    back = read_recon(tmp_path / "recon.h5")
    assert np.allclose(back.means, r.means, atol=1e-6) and back.sh_degree == 1 and back.channels == 3
    assert (back.decoder is None) == (not dynamic)
    if dynamic:
        assert back.decoder.outputs == {"dp": 3, "ds": 3, "dr": 4}
        assert np.allclose(back.decoder.layers[1][0], r.decoder.layers[1][0], atol=1e-6)
    with h5py.File(tmp_path / "recon.h5") as f:
        assert ("decoder" in f) == dynamic


def test_wrong_format_and_version(tmp_path, rng):
    write_sim(tmp_path / "sim.h5", make_sim(rng))
    with pytest.raises(FormatError, match="expected format 'gaussfluids.recon'"):
        read_recon(tmp_path / "sim.h5")
    with h5py.File(tmp_path / "sim.h5", "a") as f:
        f.attrs["version"] = 99
    with pytest.raises(FormatError, match=r"sim.h5: .*version 99 is not supported"):
        read_sim(tmp_path / "sim.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
    with pytest.raises(FormatError, match="junk.h5: not a readable HDF5"):
        read_sim(tmp_path / "junk.h5")
    with pytest.raises(InputError, match="does not exist"):
        read_sim(tmp_path / "missing.h5")


def test_nan_rejected_on_write_and_read(tmp_path, rng):
    sim = make_sim(rng)
    sim.positions[1, 3, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_sim(tmp_path / "bad.h5", sim)
    assert not (tmp_path / "bad.h5").exists()
    write_sim(tmp_path / "sim.h5", make_sim(rng))
    with h5py.File(tmp_path / "sim.h5", "a") as f:
        f["velocities"][0, 0, 0] = np.nan
    with pytest.raises(FormatError, match="'velocities' contains 1 NaN"):
        read_sim(tmp_path / "sim.h5")


def test_shape_validation(tmp_path, rng):
    write_sim(tmp_path / "sim.h5", make_sim(rng))
    with h5py.File(tmp_path / "sim.h5", "a") as f:
        del f["velocities"]
        f["velocities"] = np.zeros((4, 49, 3), np.float32)
    with pytest.raises(FormatError, match="do not match positions"):
        read_sim(tmp_path / "sim.h5")
    r = make_recon(rng)
    r.quats = r.quats[:, :3]
    with pytest.raises(FormatError, match="quats must have shape"):
        write_recon(tmp_path / "r.h5", r)


def test_atomic_write_keeps_old_file(tmp_path, rng, monkeypatch):
    path = tmp_path / "sim.h5"
    write_sim(path, make_sim(rng))
    before = path.read_bytes()
    import gf_core.formats.hdf5 as gio

    def boom(*a, **k):
        raise RuntimeError("killed mid-write")

    monkeypatch.setattr(gio, "json", type("J", (), {"dumps": staticmethod(boom)}))
    with pytest.raises(RuntimeError):
        write_sim(path, make_sim(rng, frames=2))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["sim.h5"]  # no temp files left behind


def test_simulate_writes_frames_as_it_goes_and_marks_an_interrupted_file(tmp_path):
    """Interrupted after a few frames, sim.h5 keeps them and says it is incomplete; a finished
    run's file is complete and equal to what simulate returned. Results get the normal file mode."""
    import os

    from gf_core.formats.hdf5 import read_sim
    from gf_core.sim import simulate

    out = tmp_path / "sim.h5"
    calls = {"n": 0}

    def progress(f, n, t, last):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate("water_cube", particles=300, fps=20, seconds=0.5, out=out, progress=progress)
    part = read_sim(out)
    assert not part.complete and part.num_frames == 4 and part.config["stopped_after_frames"] == 4
    sim, _ = simulate("water_cube", particles=300, fps=20, seconds=0.2, out=out)
    back = read_sim(out)
    assert back.complete and np.array_equal(back.positions, sim.positions)
    assert np.allclose(back.stats["density_err_mean"], sim.stats["density_err_mean"])
    umask = os.umask(0)
    os.umask(umask)
    assert (out.stat().st_mode & 0o777) == (0o666 & ~umask)


def test_writer_refuses_what_the_reader_refuses(tmp_path):
    from gf_core.formats.hdf5 import SimData, write_sim

    bad = SimData(positions=np.zeros((1, 2, 3)), velocities=np.zeros((1, 2, 3)), fps=-1, particle_radius=0.01)
    with pytest.raises(InputError, match="fps must be a positive number"):
        write_sim(tmp_path / "s.h5", bad)
    assert not (tmp_path / "s.h5").exists()
