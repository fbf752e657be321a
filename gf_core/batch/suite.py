"""A batch suite: jobs (gf-cli commands) with their dependencies and resources, read from TOML.

    [batch]
    out = "runs"            # the shared output folder (relative to the suite file; --out overrides)
    retries = 2             # attempts after the first, per job

    [jobs.sim]
    run = ["simulate", "water_sphere", "--particles", "300", "--out", "{dir}/sim.h5"]
    outputs = ["sim.h5"]

    [jobs.data]
    run = ["render-dataset", "{sim}/sim.h5", "--out", "{dir}", "--frames", "0:30"]
    chunks = 3              # three renders of 10 frames each, merged into one dataset
    outputs = ["transforms_train.json"]

    [jobs.recon]
    run = ["reconstruct", "{data}", "--out", "{dir}", "--seed", "0"]
    num_cpus = 2
    num_gpus = 1            # a GPU reconstruction (with --device cuda)
    memory = "8GB"

Every job writes into its own folder ``OUT/<name>`` (``{dir}``); ``{other}`` is another job's
folder and makes this job wait for it (as does ``after = [...]``). Relative paths in ``run`` start
at the suite file's folder (on a cluster: give absolute paths on the shared folder). ``outputs`` are the files the
job must leave (relative to its folder) before it counts as done.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..formats.toml_file import read_toml

# the gf-cli commands a job may run (the others are interactive, or batch itself)
COMMANDS = ("simulate", "render-dataset", "reconstruct", "evaluate", "predict", "edit", "export", "bench")
JOB_KEYS = {"run", "outputs", "after", "num_cpus", "num_gpus", "memory", "chunks", "retries"}
BATCH_KEYS = {"out", "retries"}
NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-/]*$")
PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
MERGE_MODULE = "gf_core.data.merge"


@dataclass
class Job:
    """One task: ``argv`` is the whole command (placeholders resolved), run with the job's folder
    as the place it writes."""

    name: str
    argv: list
    outputs: list = field(default_factory=list)
    after: list = field(default_factory=list)
    num_cpus: float = 1.0
    num_gpus: float = 0.0
    memory: int | None = None  # bytes
    retries: int = 2
    cwd: str | None = None  # where relative paths in argv start (None: the job's own folder)


def gf_cli_argv(args: list) -> list:
    return [sys.executable, "-m", "gf_cli.main"] + [str(a) for a in args]


def parse_memory(v, where: str) -> int | None:
    if v is None:
        return None
    if isinstance(v, int) and v > 0:
        return v
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]+)?)\s*([KMGT]?)i?B?\s*", str(v), re.IGNORECASE)
    if not m or float(m.group(1)) <= 0:
        raise InputError(where, f"memory must be bytes or a size such as \"8GB\", got {v!r}")
    return int(float(m.group(1)) * 1024 ** " KMGT".index(m.group(2).upper() or " "))


def frame_range(argv: list, where: str) -> tuple[int, int, int, int]:
    """(index of the --frames value in ``argv``, start, end, step) of a render-dataset job to split."""
    if "--frames" not in argv or argv.index("--frames") + 1 >= len(argv):
        raise InputError(where, "chunks need an explicit --frames START:END[:STEP] to split")
    i = argv.index("--frames") + 1
    parts = str(argv[i]).split(":")
    try:
        start, end = int(parts[0] or 0), int(parts[1])
        step = int(parts[2]) if len(parts) > 2 and parts[2] else 1
    except (ValueError, IndexError):
        raise InputError(where, f"chunks need --frames START:END[:STEP] with both ends given, got {argv[i]!r}") from None
    if step <= 0 or end <= start:
        raise InputError(where, f"--frames {argv[i]} selects no frames")
    return i, start, end, step


def split_frames(start: int, end: int, step: int, chunks: int) -> list[str]:
    """``chunks`` --frames ranges that together select exactly START:END:STEP, in order."""
    frames = list(range(start, end, step))
    n = min(chunks, len(frames))
    bounds = [round(k * len(frames) / n) for k in range(n + 1)]
    return [f"{frames[bounds[k]]}:{frames[bounds[k + 1] - 1] + 1}:{step}" for k in range(n)]


def _resolve(arg, names: set, dirs: dict, here: str, where: str, deps: set) -> str:
    def sub(m):
        key = m.group(1)
        if key == "dir":
            return str(dirs[here])
        if key not in names:
            raise InputError(where, f"{{{key}}} names no job (jobs: {', '.join(sorted(names))})")
        if key == here:
            raise InputError(where, f"{{{key}}} is the job itself; use {{dir}}")
        deps.add(key)
        return str(dirs[key])
    return PLACEHOLDER.sub(sub, str(arg))


def load_suite(path, out: Path | None = None) -> tuple[list[Job], Path]:
    """The suite's jobs (chunked renders expanded, placeholders resolved, in an order where every
    job comes after what it needs) and the output folder."""
    path = Path(path)
    doc = read_toml(path, "suite file")
    unknown = set(doc) - {"batch", "jobs"}
    if unknown:
        raise InputError(path, f"unknown top-level table(s) {', '.join(sorted(unknown))} (expected [batch], [jobs.NAME])")
    batch = doc.get("batch", {})
    if set(batch) - BATCH_KEYS:
        raise InputError(path, f"[batch]: unknown key(s) {', '.join(sorted(set(batch) - BATCH_KEYS))}")
    out = Path(out) if out is not None else path.parent / batch.get("out", "batch_out")
    specs = doc.get("jobs", {})
    if not specs:
        raise InputError(path, "has no jobs ([jobs.NAME] tables with a run = [...] command)")
    return expand(specs, out, str(path), default_retries=batch.get("retries", 2), cwd=path.parent.resolve()), out


def expand(specs: dict, out: Path, where: str, *, default_retries: int = 2, cwd: Path | None = None) -> list[Job]:
    """Jobs from ``{name: spec}`` (the [jobs] table's form), placeholders resolved against ``out``;
    relative paths in the commands start at ``cwd`` (the suite file's folder)."""
    out = Path(out).resolve()
    names = set(specs)
    # chunked renders: NAME.chunkK render frame ranges, NAME merges them
    dirs = {}
    for name, spec in specs.items():
        w = f"{where}: job {name!r}"
        if not isinstance(spec, dict):
            raise InputError(w, "must be a table")
        if not NAME.match(name) or ".." in name.split("/"):
            raise InputError(w, "a job name is letters, digits and _ . - / (a path below the output folder)")
        if set(spec) - JOB_KEYS:
            raise InputError(w, f"unknown key(s) {', '.join(sorted(set(spec) - JOB_KEYS))} "
                                f"(known: {', '.join(sorted(JOB_KEYS))})")
        run = spec.get("run")
        if not isinstance(run, list) or not run or not all(isinstance(a, (str, int, float)) for a in run):
            raise InputError(w, "run must be a list of gf-cli arguments, e.g. [\"simulate\", \"water_sphere\", ...]")
        if run[0] not in COMMANDS:
            raise InputError(w, f"run: {run[0]!r} is not a gf-cli command a job may run ({', '.join(COMMANDS)})")
        dirs[name] = out / name
    jobs = []
    for name, spec in specs.items():
        w = f"{where}: job {name!r}"
        deps = set()
        for a in spec.get("after", []):
            if a not in names:
                raise InputError(w, f"after: {a!r} names no job")
            deps.add(a)
        try:
            retries = int(spec.get("retries", default_retries))
            num_cpus = float(spec.get("num_cpus", 1))
            num_gpus = float(spec.get("num_gpus", 0))
        except (TypeError, ValueError):
            raise InputError(w, "retries, num_cpus and num_gpus are numbers") from None
        if retries < 0 or num_cpus <= 0 or num_gpus < 0:
            raise InputError(w, "retries >= 0, num_cpus > 0 and num_gpus >= 0")
        memory = parse_memory(spec.get("memory"), w)
        outputs = [str(o) for o in spec.get("outputs", [])]
        for o in outputs:
            if Path(o).is_absolute() or ".." in Path(o).parts:
                raise InputError(w, f"outputs: {o!r} must be a path inside the job's folder")
        args = [_resolve(a, names, dirs, name, w, deps) for a in spec["run"]]
        common = dict(num_cpus=num_cpus, num_gpus=num_gpus, memory=memory, retries=retries,
                      cwd=str(cwd) if cwd else None)
        chunks = spec.get("chunks", 1)
        if not isinstance(chunks, int) or chunks < 1:
            raise InputError(w, f"chunks must be a whole number >= 1, got {chunks!r}")
        if chunks == 1:
            jobs.append(Job(name, gf_cli_argv(args), outputs, sorted(deps), **common))
            continue
        if args[0] != "render-dataset":
            raise InputError(w, "chunks split a render-dataset job's frames; this job runs " + args[0])
        i, start, end, step = frame_range(args, w)
        parts = []
        for k, frames in enumerate(split_frames(start, end, step, chunks)):
            cname = f"{name}.chunk{k}"
            cdir = out / cname
            cargs = [str(cdir) if a == str(dirs[name]) else a for a in args]
            cargs[i] = frames
            jobs.append(Job(cname, gf_cli_argv(cargs), [], sorted(deps), **common))
            parts.append(cname)
        merge = [sys.executable, "-m", MERGE_MODULE, "--out", str(dirs[name]), "--frames", args[i]] + \
            [str(out / p) for p in parts]
        jobs.append(Job(name, merge, outputs, parts, num_cpus=1.0, num_gpus=0.0, memory=None, retries=retries,
                        cwd=str(cwd) if cwd else None))
    return ordered(jobs, where)


def ordered(jobs: list[Job], where: str) -> list[Job]:
    """``jobs`` with every job after those it needs; a cycle is an error that names it."""
    by = {j.name: j for j in jobs}
    done, out, visiting = set(), [], []

    def visit(j):
        if j.name in done:
            return
        if j.name in visiting:
            cyc = visiting[visiting.index(j.name):] + [j.name]
            raise InputError(where, f"jobs wait for each other in a cycle: {' -> '.join(cyc)}")
        visiting.append(j.name)
        for d in j.after:
            visit(by[d])
        visiting.pop()
        done.add(j.name)
        out.append(j)

    for j in jobs:
        visit(j)
    return out
