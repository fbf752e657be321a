"""gf-cli batch: suites read with clear errors, jobs run N at a time with retries and skips, and a
tiny suite (simulate -> render in two chunks -> reconstruct -> evaluate) on a local Ray instance
equal to the same suite run locally."""

import importlib.util
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gf_cli.main import main
from gf_core.batch import Job, LocalExecutor, is_done, load_suite, run_jobs, status
from gf_core.batch.suite import split_frames
from gf_core.errors import InputError
from helpers import assert_same_render


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def py_job(name, code, **kw) -> Job:
    return Job(name, [sys.executable, "-c", code], **kw)


# ---- suites ---------------------------------------------------------------------------------------
def test_split_frames_covers_the_range_in_order():
    for start, end, step, n in ((0, 30, 1, 3), (0, 10, 3, 2), (5, 12, 2, 4), (0, 3, 1, 5)):
        got = []
        for r in split_frames(start, end, step, n):
            a, b, s = map(int, r.split(":"))
            got += list(range(a, b, s))
        assert got == list(range(start, end, step)), (start, end, step, n)


def test_suite_expands_chunks_resolves_folders_and_orders_jobs(tmp_path):
    suite = write(tmp_path / "s.toml", """
[batch]
out = "o"
[jobs.eval]
run = ["evaluate", "{recon}", "--dataset", "{data}", "--out", "{dir}"]
[jobs.recon]
run = ["reconstruct", "{data}", "--out", "{dir}"]
num_gpus = 1
memory = "2GB"
[jobs.data]
run = ["render-dataset", "{sim}/sim.h5", "--out", "{dir}", "--frames", "0:10"]
chunks = 3
[jobs.sim]
run = ["simulate", "water_sphere", "--out", "{dir}/sim.h5"]
""")
    jobs, out = load_suite(suite)
    assert out == tmp_path / "o"
    names = [j.name for j in jobs]
    assert names.index("sim") < names.index("data.chunk0") < names.index("data") < names.index("recon") < \
        names.index("eval")
    by = {j.name: j for j in jobs}
    assert by["data"].after == ["data.chunk0", "data.chunk1", "data.chunk2"]
    frames = [by[f"data.chunk{k}"].argv[by[f"data.chunk{k}"].argv.index("--frames") + 1] for k in range(3)]
    assert frames == ["0:3:1", "3:7:1", "7:10:1"]
    assert str((tmp_path / "o" / "data.chunk1").resolve()) in by["data.chunk1"].argv
    assert by["recon"].argv[-3:] == [str((tmp_path / "o" / "data").resolve()), "--out",
                                     str((tmp_path / "o" / "recon").resolve())]
    assert by["recon"].num_gpus == 1 and by["recon"].memory == 2 * 1024 ** 3
    assert sorted(by["eval"].after) == ["data", "recon"]
    assert all(j.cwd == str(tmp_path.resolve()) for j in jobs)  # relative paths start at the suite's folder


@pytest.mark.parametrize("body, message", [
    ('[jobs.a]\nrun = ["simulate", "{b}"]', "{b} names no job"),
    ('[jobs.a]\nrun = ["demo"]', "'demo' is not a gf-cli command a job may run"),
    ('[jobs.a]\nrun = ["simulate"]\ncolour = 1', "unknown key(s) colour"),
    ('[jobs.a]\nrun = ["simulate", "{b}"]\n[jobs.b]\nrun = ["simulate", "{a}"]', "cycle: a -> b -> a"),
    ('[jobs.a]\nrun = ["render-dataset", "x"]\nchunks = 2', "chunks need an explicit --frames"),
    ('[jobs.a]\nrun = ["reconstruct", "x"]\nchunks = 2', "chunks split a render-dataset job's frames"),
    ('[jobs.a]\nrun = ["simulate"]\nmemory = "lots"', "memory must be bytes or a size"),
    ('[jobs.a]\nrun = ["simulate"]\nafter = ["z"]', "after: 'z' names no job"),
    ('[jobs.a]\nrun = ["simulate"]\noutputs = ["../x"]', "must be a path inside the job's folder"),
    ('[jobs.a]\nrun = "simulate"', "run must be a list of gf-cli arguments"),
    ("[batch]\nout = 'o'", "has no jobs"),
    ("[jobs.a\nrun = 1", "not valid TOML"),
])
def test_bad_suites_give_one_clear_line(tmp_path, capsys, body, message):
    suite = write(tmp_path / "s.toml", body)
    with pytest.raises(InputError, match=None) as e:
        load_suite(suite)
    assert message in str(e.value) and str(suite) in str(e.value)
    assert main(["batch", str(suite)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


# ---- the runner -----------------------------------------------------------------------------------
def test_retries_blocks_and_skips_what_is_done(tmp_path):
    out = tmp_path / "o"
    flag = tmp_path / "failed_once"
    jobs = [
        py_job("a", "open('a.txt', 'w').write('1')", outputs=["a.txt"]),
        # fails on its first attempt, then succeeds: retried
        py_job("b", f"import os, sys\nif not os.path.exists({str(flag)!r}):\n    open({str(flag)!r}, 'w').close()\n"
                    "    open('half.txt', 'w').write('x'); sys.exit(3)\nopen('b.txt', 'w').write('2')",
               outputs=["b.txt"], after=["a"], retries=1),
        py_job("c", "import sys; sys.exit(1)", after=["a"], retries=1),       # fails every time
        py_job("d", "open('d.txt', 'w').write('4')", after=["c"]),             # needs c: blocked
        py_job("e", "pass", outputs=["never.txt"], retries=0),               # leaves no output: failed
        Job("f", [sys.executable, "-c", "open('rel.txt', 'w').write('6')"], cwd=str(tmp_path)),  # relative to cwd
    ]
    lines = []
    rows = {r["job"]: r for r in run_jobs(jobs, out, LocalExecutor(2), log=lines.append)}
    assert rows["a"]["state"] == "done" and rows["a"]["attempts"] == 1
    assert rows["b"]["state"] == "done" and rows["b"]["attempts"] == 2
    assert not (out / "b" / "half.txt").exists()  # each attempt starts from an empty folder
    assert rows["c"]["state"] == "failed" and rows["c"]["attempts"] == 2 and "exit 1" in rows["c"]["note"]
    assert rows["d"]["state"] == "blocked" and rows["d"]["attempts"] == 0
    assert rows["e"]["state"] == "failed" and "left no never.txt" in rows["e"]["note"]
    assert rows["f"]["state"] == "done" and (tmp_path / "rel.txt").read_text() == "6"
    assert any("b: pending (attempt 1 failed: exit 3" in ln for ln in lines)
    assert (out / "_batch" / "logs" / "b.1.log").exists() and (out / "_batch" / "logs" / "b.2.log").exists()
    # a re-run skips the finished jobs, retries the others
    rows = {r["job"]: r for r in run_jobs(jobs, out, LocalExecutor(2), log=lines.append)}
    assert rows["a"]["state"] == rows["b"]["state"] == "done earlier" and rows["a"]["attempts"] == 0
    # what is not done: a changed command, a file that lost bytes, an output without its record
    assert is_done(jobs[0], out)
    assert not is_done(py_job("a", "pass", outputs=["a.txt"]), out)
    (out / "b" / "b.txt").write_text("")
    assert not is_done(jobs[1], out)
    (out / "a" / "_job.json").unlink()
    assert not is_done(jobs[0], out)
    st = {r["job"]: r["state"] for r in status(jobs, out)}
    assert st["a"] == "changed since (not done)" and st["c"] == "failed" and st["d"] == "blocked"


def test_local_runs_at_most_n_at_a_time(tmp_path):
    code = ("import os, time\nopen(os.path.join({d!r}, str(os.getpid())), 'w').close()\n"
            "n = len(os.listdir({d!r}))\nopen('n.txt', 'w').write(str(n))\ntime.sleep(0.5)\n"
            "os.remove(os.path.join({d!r}, str(os.getpid())))")
    live = tmp_path / "live"
    live.mkdir()
    jobs = [py_job(f"j{k}", code.format(d=str(live)), outputs=["n.txt"]) for k in range(5)]
    rows = run_jobs(jobs, tmp_path / "o", LocalExecutor(2), log=lambda s: None)
    assert all(r["state"] == "done" for r in rows)
    assert max(int((tmp_path / "o" / f"j{k}" / "n.txt").read_text()) for k in range(5)) <= 2


# ---- a real suite on Ray --------------------------------------------------------------------------
SUITE = """
[batch]
retries = 2

[jobs.sim]
run = ["simulate", "water_sphere", "--particles", "300", "--fps", "20", "--seconds", "0.25", "--out", "{dir}/sim.h5",
       "--quiet"]
outputs = ["sim.h5"]

[jobs.data]
run = ["render-dataset", "{sim}/sim.h5", "--out", "{dir}", "--views", "2", "--test-views", "1", "--resolution", "64",
       "--samples", "2", "--frames", "0:6"]
chunks = 2
outputs = ["transforms_train.json", "transforms_test.json"]

[jobs.recon]
run = ["reconstruct", "{data}", "--out", "{dir}", "--iterations", "150", "--init-particles", "250",
       "--max-particles", "400", "--seed", "0", "--quiet"]
outputs = ["recon.h5"]
num_cpus = 1
memory = "2GB"

[jobs.eval]
run = ["evaluate", "{recon}", "--dataset", "{data}", "--out", "{dir}"]
outputs = ["eval.json"]
"""


def _kill_once(match: str, seen: list, stop: threading.Event):
    """SIGKILL the first process whose command line holds ``match`` (a job mid-way)."""
    while not stop.is_set():
        for pid in os.listdir("/proc"):
            if not pid.isdigit():
                continue
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if match in cmd and "gf_cli.main" in cmd:
                time.sleep(1.0)  # mid-way, not at its start
                try:
                    os.kill(int(pid), signal.SIGKILL)
                    seen.append(int(pid))
                except ProcessLookupError:
                    continue
                return
        time.sleep(0.05)


LOCAL = """
[jobs.single]
run = ["render-dataset", "{ray}/sim/sim.h5", "--out", "{dir}", "--views", "2", "--test-views", "1", "--resolution", "64",
       "--samples", "2", "--frames", "0:6"]

[jobs.recon]
run = ["reconstruct", "{ray}/data", "--out", "{dir}", "--iterations", "150", "--init-particles", "250",
       "--max-particles", "400", "--seed", "0", "--quiet"]
num_cpus = 1
"""


@pytest.mark.blender
@pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="render-dataset needs the bpy module")
def test_suite_on_ray_retries_a_killed_job_and_equals_a_local_run(tmp_path, capsys):
    import cv2
    import ray

    from gf_core.batch import RayExecutor
    from gf_core.formats.hdf5 import read_recon

    suite = write(tmp_path / "suite.toml", SUITE)
    ray_out = (tmp_path / "ray").resolve()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        killed, stop = [], threading.Event()
        watcher = threading.Thread(target=_kill_once, args=(f"reconstruct {ray_out / 'data'}", killed, stop))
        watcher.start()
        jobs, out = load_suite(suite, ray_out)
        assert [j.name for j in jobs] == ["sim", "data.chunk0", "data.chunk1", "data", "recon", "eval"]
        lines = []

        def log(line):  # kept for the checks, shown when the test fails
            lines.append(line)
            print(line, flush=True)

        rows = {r["job"]: r for r in run_jobs(jobs, out, RayExecutor(), log=log)}
        stop.set()
        watcher.join()
        assert killed, "the reconstruction ended before it could be killed"
        assert all(r["state"] == "done" for r in rows.values()), rows
        assert rows["recon"]["attempts"] == 2 and rows["sim"]["attempts"] == 1
        assert any("recon: pending (attempt 1 failed: killed by signal 9" in ln for ln in lines), lines
        # a re-run skips every finished job
        again = run_jobs(jobs, out, RayExecutor(), log=log)
        assert {r["state"] for r in again} == {"done earlier"} and all(r["attempts"] == 0 for r in again)
    finally:
        ray.shutdown()
    assert main(["batch", "status", str(suite), "--out", str(ray_out)]) == 0
    assert "6 of 6 jobs done" in capsys.readouterr().out

    # locally, 2 at a time: one render of every frame, and the reconstruction of the merged dataset
    local = write(tmp_path / "local.toml", LOCAL.replace("{ray}", str(ray_out)))
    assert main(["batch", str(local), "--local", "2", "--out", str(tmp_path / "local")]) == 0
    merged, one = ray_out / "data", tmp_path / "local" / "single"
    pngs = sorted(p.relative_to(one) for p in one.rglob("*.png"))
    assert len(pngs) == 18 and sorted(p.relative_to(merged) for p in merged.rglob("*.png")) == pngs
    for name in ("transforms_train.json", "transforms_test.json", "render_source.json", "gt_sim.h5"):
        assert (merged / name).read_bytes() == (one / name).read_bytes(), name
    for rel in pngs:  # as two renders of the same seed agree (tests/helpers.py)
        assert_same_render(cv2.imread(str(merged / rel), cv2.IMREAD_UNCHANGED),
                           cv2.imread(str(one / rel), cv2.IMREAD_UNCHANGED), rel)
    assert json.loads((merged / "manifest.json").read_text())["frames"] == list(range(6))
    # the reconstruction on Ray (after its retry) is the local one: same data, seed and threads
    a, b = read_recon(ray_out / "recon" / "recon.h5"), read_recon(tmp_path / "local" / "recon" / "recon.h5")
    assert a.num_particles == b.num_particles
    for k in ("means", "log_scales", "quats", "logit_opacity", "sh"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    assert json.loads((ray_out / "eval" / "eval.json").read_text())["test"]["psnr_mean"] > 10
