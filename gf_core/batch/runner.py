"""Runs a suite's jobs: N at a time on this machine, or as Ray tasks on a cluster.

Each attempt of a job starts from an empty folder ``OUT/<name>``, runs the job's command there
with as many threads as the job has CPUs, and only when the command succeeds and left its
``outputs`` is ``_job.json`` written (atomically) beside them: the command and the size of every
file. A job is done when that record is there, names the same command and every file still has
its size; a re-run skips it. A failed attempt (an error, a killed process, a lost Ray worker) is
retried up to the job's ``retries``; jobs that need a failed one are reported as blocked. The
driver keeps the state of every job in ``OUT/_batch/state.json`` (``gf-cli batch status``) and
each attempt's output in ``OUT/_batch/logs/``.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

from ..formats.hdf5 import atomic_write_text
from .suite import Job

DONE_FILE = "_job.json"
STATE_DIR = "_batch"
DONE, SKIPPED, FAILED, BLOCKED = "done", "done earlier", "failed", "blocked"


def job_dir(out: Path, job: Job) -> Path:
    return Path(out) / job.name


def log_path(out: Path, job: Job, attempt: int) -> Path:
    return Path(out) / STATE_DIR / "logs" / f"{job.name.replace('/', '__')}.{attempt}.log"


def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(data, indent=1))


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): p.stat().st_size for p in sorted(d.rglob("*")) if p.is_file() and p.name != DONE_FILE}


def is_done(job: Job, out: Path) -> bool:
    """The job's folder holds a complete result of this very command."""
    d = job_dir(out, job)
    try:
        rec = json.loads((d / DONE_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    if rec.get("argv") != job.argv:
        return False
    files = rec.get("files", {})
    if any(o not in files for o in job.outputs):
        return False
    for rel, size in files.items():
        p = d / rel
        if not p.is_file() or p.stat().st_size != size:
            return False
    return True


def attempt(job: Job, out: str, number: int) -> dict:
    """One attempt of ``job`` (in this process, a pool thread or a Ray worker): the result record."""
    out = Path(out)
    d = job_dir(out, job)
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    logf = log_path(out, job, number)
    logf.parent.mkdir(parents=True, exist_ok=True)
    threads = str(max(1, int(job.num_cpus)))
    env = dict(os.environ, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    t0 = time.time()
    with open(logf, "w") as f:
        f.write("$ " + " ".join(job.argv) + "\n")
        f.flush()
        rc = subprocess.run(job.argv, stdout=f, stderr=subprocess.STDOUT, env=env,
                            cwd=job.cwd or d).returncode
    wall = time.time() - t0
    res = {"ok": False, "rc": rc, "wall_s": wall, "host": socket.gethostname(), "log": str(logf)}
    if rc != 0:
        tail = logf.read_text(errors="replace").strip().splitlines()[-3:]
        res["why"] = (f"killed by signal {-rc}" if rc < 0 else f"exit {rc}") + (": " + " | ".join(tail) if tail else "")
        return res
    missing = [o for o in job.outputs if not (d / o).exists()]
    if missing:
        res["why"] = f"finished but left no {', '.join(missing)}"
        return res
    _write_json(d / DONE_FILE, {"argv": job.argv, "files": _files(d), "wall_s": wall, "host": res["host"],
                                "attempt": number, "finished": time.strftime("%Y-%m-%dT%H:%M:%S")})
    res["ok"] = True
    return res


class LocalExecutor:
    """``n`` jobs at a time on this machine (each a process; threads only wait for them)."""

    def __init__(self, n: int):
        self.capacity = n
        self.pool = cf.ThreadPoolExecutor(max_workers=n)
        self.where = f"this machine, {n} at a time"

    def submit(self, job: Job, out: Path, number: int):
        return self.pool.submit(attempt, job, str(out), number)

    def wait_any(self, handles):
        done, _ = cf.wait(list(handles), return_when=cf.FIRST_COMPLETED)
        return list(done)

    def result(self, handle) -> dict:
        try:
            return handle.result()
        except Exception as e:  # the attempt itself broke (a full disk, a folder it may not write)
            return {"ok": False, "rc": None, "why": f"{type(e).__name__}: {e}"}

    def close(self):
        self.pool.shutdown(wait=True)


class RayExecutor:
    """Each attempt a Ray task with the job's num_cpus / num_gpus / memory. Connects to
    ``address`` ("auto": the cluster started with `ray start`), or uses a Ray already initialised."""

    def __init__(self, address: str | None = None):
        try:
            import ray
        except ImportError:
            from ..errors import GFError

            raise GFError("--ray needs Ray: pip install -e '.[cluster]'") from None
        self.ray = ray
        if not ray.is_initialized():
            ray.init(address=address, log_to_driver=False)
        self.capacity = None  # Ray queues tasks until their resources are free
        self.remote = ray.remote(max_retries=0)(attempt)  # retries are counted here, with the reason
        res = ray.cluster_resources()
        self.where = f"Ray cluster, {res.get('CPU', 0):g} CPUs, {res.get('GPU', 0):g} GPUs"

    def submit(self, job: Job, out: Path, number: int):
        opts = {"num_cpus": job.num_cpus, "num_gpus": job.num_gpus}
        if job.memory:
            opts["memory"] = job.memory
        return self.remote.options(**opts).remote(job, str(Path(out).resolve()), number)

    def wait_any(self, handles):
        ready, _ = self.ray.wait(list(handles), num_returns=1)
        return ready

    def result(self, handle) -> dict:
        try:
            return self.ray.get(handle)
        except self.ray.exceptions.RayError as e:  # a worker or node lost, a task cancelled
            return {"ok": False, "rc": None, "why": f"Ray: {type(e).__name__}: {str(e).splitlines()[0]}"}

    def close(self):
        pass


def _stamp() -> str:
    return time.strftime("%H:%M:%S")


def run_jobs(jobs: list[Job], out: Path, executor, log=print) -> list[dict]:
    """Every job run (or skipped when done), dependencies first. One summary row per job."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = {j.name: {"job": j.name, "state": "pending", "attempts": 0, "wall_s": 0.0, "note": ""} for j in jobs}
    by = {j.name: j for j in jobs}
    state_file = out / STATE_DIR / "state.json"

    def say(name, state, note=""):
        rows[name].update(state=state, note=note)
        log(f"[{_stamp()}] {name}: {state}" + (f" ({note})" if note else ""))
        _write_json(state_file, {"updated": time.strftime("%Y-%m-%dT%H:%M:%S"), "where": executor.where,
                                 "jobs": list(rows.values())})

    log(f"batch: {len(jobs)} jobs on {executor.where}; output in {out}")
    for j in jobs:
        if is_done(j, out):
            say(j.name, SKIPPED)
    running = {}
    while True:
        for j in jobs:
            r = rows[j.name]
            if r["state"] != "pending":
                continue
            bad = [d for d in j.after if rows[d]["state"] in (FAILED, BLOCKED)]
            if bad:
                say(j.name, BLOCKED, f"needs {', '.join(bad)}")
            elif all(rows[d]["state"] in (DONE, SKIPPED) for d in j.after) and \
                    (executor.capacity is None or len(running) < executor.capacity):
                r["attempts"] += 1
                running[executor.submit(j, out, r["attempts"])] = j.name
                say(j.name, "running", f"attempt {r['attempts']} of {j.retries + 1}")
        if not running:
            break
        for h in executor.wait_any(running):
            name = running.pop(h)
            res = executor.result(h)
            r = rows[name]
            r["wall_s"] += res.get("wall_s", 0.0)
            if res["ok"]:
                say(name, DONE, f"{res['wall_s']:.1f} s on {res.get('host', '?')}")
            elif r["attempts"] <= by[name].retries:
                say(name, "pending", f"attempt {r['attempts']} failed: {res['why']}; retrying")
            else:
                say(name, FAILED, f"{r['attempts']} attempts; last: {res['why']}")
    executor.close()
    return list(rows.values())


def status(jobs: list[Job], out: Path) -> list[dict]:
    """What is done on disk now, and what the last run said of the rest."""
    out = Path(out)
    try:
        last = {r["job"]: r for r in json.loads((out / STATE_DIR / "state.json").read_text())["jobs"]}
    except (OSError, json.JSONDecodeError, KeyError):
        last = {}
    rows = []
    for j in jobs:
        r = dict(last.get(j.name, {"job": j.name, "attempts": 0, "wall_s": 0.0, "note": ""}))
        r["state"] = DONE if is_done(j, out) else (r.get("state", "not started") if r.get("state") not in
                                                   (DONE, SKIPPED) else "changed since (not done)")
        rows.append(r)
    return rows


def summary_table(rows: list[dict]) -> str:
    w = max([len(r["job"]) for r in rows] + [3])
    lines = [f"{'job':<{w}}  {'state':<14} {'attempts':>8} {'wall s':>8}  note", "-" * (w + 40)]
    for r in rows:
        lines.append(f"{r['job']:<{w}}  {r['state']:<14} {r.get('attempts', 0):>8} {r.get('wall_s', 0.0):>8.1f}  "
                     f"{r.get('note', '')}")
    return "\n".join(lines)
