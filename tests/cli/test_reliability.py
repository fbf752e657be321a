"""Bad input from every key of every format and from extreme options: one clear line, exit code 2.

The cases come from ``tests/cli/reliability_cases.py`` (a good base scene, each key mutated). A case
passes when the command either works (exit 0: the change was harmless, e.g. an optional key
removed) or refuses with exactly one line ``gf-cli COMMAND: error: ...`` and exit code 2; a
traceback (any other exception leaving the command) fails it. Cases marked ``must_refuse`` (a
truncated or non-UTF-8 file, a torn image, a huge option) pass only with exit code 2.
"""

import contextlib
import io
import shutil
from collections import Counter

import pytest

from gf_cli.main import main
from gf_core.errors import InputError
from gf_core.recon.config import make_config

from reliability_cases import cases, make_base

GROUPS = ("dataset", "video", "pinf", "colmap", "sim", "recon", "checkpoint", "config", "option")
# configs that the reader accepts train for two iterations each; every this-many-th of them runs
CONFIG_RUN_EVERY = 8


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_base(tmp_path_factory.mktemp("reliability"))


@pytest.fixture(scope="module")
def all_cases(base):
    return cases(base)


def run_case(case, argv):
    """(outcome, message): 'refused' / 'accepted' / 'bad'."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            rc = main(argv)
    except SystemExit as e:  # argparse: its usage line and exit code 2
        return ("refused", "argparse") if e.code == 2 else ("bad", f"exit {e.code}")
    except BaseException as e:  # noqa: BLE001 -- any exception leaving the command is the failure
        return "bad", f"traceback: {type(e).__name__}: {str(e)[:200]}"
    lines = [ln for ln in err.getvalue().strip().splitlines() if f"gf-cli {argv[0]}: error:" in ln]
    if rc == 0:
        return ("bad", "exit 0, but this input must be refused") if case.must_refuse else ("accepted", "")
    if rc == 2 and len(lines) == 1:
        return "refused", lines[0]
    return "bad", f"exit {rc}, stderr {err.getvalue()[-300:]!r}"


@pytest.mark.parametrize("group", GROUPS)
def test_bad_input_gives_one_line_and_exit_2(group, all_cases, tmp_path):
    tally, bad, accepted_configs = Counter(), [], 0
    for k, case in enumerate(c for c in all_cases if group in c.tags):
        tmp = tmp_path / f"c{k}"
        tmp.mkdir()
        argv = case.make(tmp)
        if group == "config":  # the reader decides; accepted configs are valid and train
            path = argv[argv.index("--config") + 1]
            try:
                make_config("water", path)
            except InputError:
                pass
            else:
                accepted_configs += 1
                if accepted_configs % CONFIG_RUN_EVERY:
                    tally["accepted (read only)"] += 1
                    shutil.rmtree(tmp)
                    continue
        outcome, msg = run_case(case, argv)
        tally[outcome] += 1
        if outcome == "bad":
            bad.append(f"{case.id}: {msg}")
        shutil.rmtree(tmp, ignore_errors=True)
    print(group, dict(tally))
    assert not bad, f"{len(bad)} of {sum(tally.values())} cases:\n" + "\n".join(bad[:30])
    assert tally["refused"] > 0


def test_the_suite_is_broad(all_cases):
    """At least 300 generated bad inputs over every command that reads a file or takes a size."""
    ids = Counter(c.tags[0] for c in all_cases)
    assert sum(ids.values()) >= 300 and set(ids) == set(GROUPS), ids
    print(dict(ids), sum(ids.values()))


# ---- killed and resumed --------------------------------------------------------------------------
def _gf(*args, **kw):
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-m", "gf_cli.main", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _wait_for(pred, proc, timeout=120.0):
    import time

    t0 = time.time()
    while not pred():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < timeout
        time.sleep(0.05)


def _rows(run):
    import json

    return [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()]


def test_reconstruct_killed_anywhere_resumes_to_the_uninterrupted_result(base, tmp_path):
    """SIGKILL after the first checkpoint at a random point, then --resume: the same recon.h5 as an
    uninterrupted run, and metrics.jsonl with every logged iteration once."""
    import random
    import signal
    import time

    import numpy as np

    from gf_core.formats.hdf5 import read_recon

    cfg = tmp_path / "c.toml"
    cfg.write_text(base["toml"].read_text().replace("iterations = 2", "iterations = 240")
                   .replace("checkpoint_every = 2", "checkpoint_every = 60").replace("log_every = 1", "log_every = 10"))
    common = [base["ds"], "--config", cfg, "--quiet"]
    a = _gf("reconstruct", *common, "--out", tmp_path / "a")
    assert a.wait() == 0, a.communicate()
    b = _gf("reconstruct", *common, "--out", tmp_path / "b")
    _wait_for(lambda: (tmp_path / "b" / "checkpoint.pt").exists(), b)
    time.sleep(random.Random(0).uniform(0.0, 1.0))
    b.send_signal(signal.SIGKILL)
    b.wait()
    assert not (tmp_path / "b" / "recon.h5").exists(), "the run ended before the kill; the test needs a longer run"
    r = _gf("reconstruct", *common, "--out", tmp_path / "b", "--resume")
    out, err = r.communicate()
    assert r.returncode == 0, err
    assert "resumed from" in out + err
    ra, rb = read_recon(tmp_path / "a" / "recon.h5"), read_recon(tmp_path / "b" / "recon.h5")
    assert ra.num_particles == rb.num_particles and np.allclose(ra.means, rb.means, atol=1e-5)
    its_a, its_b = [x["iteration"] for x in _rows(tmp_path / "a")], [x["iteration"] for x in _rows(tmp_path / "b")]
    assert its_b == its_a, (its_a, its_b)


def test_a_second_process_on_one_run_folder_is_refused(base, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(base["toml"].read_text().replace("iterations = 2", "iterations = 100000"))
    first = _gf("reconstruct", base["ds"], "--config", cfg, "--quiet", "--out", tmp_path / "r")
    try:
        _wait_for(lambda: (tmp_path / "r" / "metrics.jsonl").exists(), first)
        second = _gf("reconstruct", base["ds"], "--config", cfg, "--quiet", "--out", tmp_path / "r", "--resume")
        out, err = second.communicate()
        assert second.returncode == 2 and "another process (pid" in err and len(err.strip().splitlines()) == 1, err
        assert first.poll() is None  # the first one goes on, untouched
    finally:
        first.kill()
        first.wait()



def test_a_second_process_on_one_simulation_is_refused_and_the_first_completes(tmp_path):
    """Two `simulate` writing one --out: the second is refused in one line while the first runs;
    the first's file is complete, frame for frame, and its lock is gone after it."""
    import h5py

    from gf_core.formats.hdf5 import read_sim

    out = tmp_path / "s.h5"
    args = ["simulate", "water_cube", "--particles", "1500", "--fps", "20", "--seconds", "5", "--quiet", "--out", out]
    first = _gf(*args)

    def started():
        try:
            with h5py.File(out, "r", locking=False) as f:
                return f["times"].shape[0] >= 2
        except Exception:  # noqa: BLE001 -- not created yet, or caught between two writes
            return False
    _wait_for(started, first)
    second = _gf(*args)
    _, err = second.communicate()
    assert second.returncode == 2 and "another process (pid" in err and len(err.strip().splitlines()) == 1, err
    assert first.wait() == 0, first.communicate()
    sim = read_sim(out)
    assert sim.complete and sim.num_frames == 101
    assert not (tmp_path / ".s.h5.lock").exists()


def test_a_dataset_being_rendered_is_not_rendered_into_by_a_second_process(base, tmp_path):
    """While one process holds a dataset folder, `render-dataset` into it is refused in one line
    before Blender starts, and nothing is written there."""
    import subprocess
    import sys
    import time

    out = tmp_path / "ds"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "from gf_core.formats.hdf5 import output_lock\n"
        f"with output_lock({str(out)!r}, 'dataset'):\n"
        "    print('held', flush=True)\n"
        "    time.sleep(60)\n")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        t0 = time.time()
        second = _gf("render-dataset", base["sim"], "--out", out, "--resolution", "16", "--views", "2")
        _, err = second.communicate()
        assert second.returncode == 2 and "another process (pid" in err and len(err.strip().splitlines()) == 1, err
        assert time.time() - t0 < 30 and not out.exists()
    finally:
        holder.kill()
        holder.wait()

def test_simulate_killed_anywhere_resumes_from_its_last_frame_to_the_uninterrupted_result(tmp_path):
    """SIGKILL after a random number of frames: the file says incomplete and holds the frames so
    far; the same command again goes on from the last frame (not from the start) and ends with
    exactly the uninterrupted run's frames."""
    import signal

    import numpy as np

    from gf_core.formats.hdf5 import read_sim

    args = ["simulate", "water_cube", "--particles", "400", "--fps", "20", "--seconds", "2"]
    a = _gf(*args, "--out", tmp_path / "a.h5")
    assert a.wait() == 0, a.communicate()
    b = _gf(*args, "--out", tmp_path / "b.h5")

    def frames():
        import h5py

        try:  # the writer holds the file open: read without HDF5's file lock
            with h5py.File(tmp_path / "b.h5", "r", locking=False) as f:
                return f["times"].shape[0] >= 5
        except Exception:  # noqa: BLE001 -- not created yet, or caught between two writes
            return False
    _wait_for(frames, b)
    b.send_signal(signal.SIGKILL)
    b.wait()
    part = read_sim(tmp_path / "b.h5")
    full = read_sim(tmp_path / "a.h5")
    assert not part.complete and 5 <= part.num_frames < full.num_frames
    assert np.array_equal(part.positions, full.positions[: part.num_frames])
    again = _gf(*args, "--out", tmp_path / "b.h5")
    out, err = again.communicate()
    assert again.returncode == 0, err
    done = read_sim(tmp_path / "b.h5")
    assert f"resumed after frame {part.num_frames - 1}" in out and done.config["resumed_after_frame"] == part.num_frames - 1
    assert done.complete and np.array_equal(done.positions, full.positions)
    assert np.array_equal(done.velocities, full.velocities) and np.array_equal(done.times, full.times)
    for k in ("density_err_mean", "kinetic"):
        np.testing.assert_array_equal(done.stats[k], full.stats[k])
