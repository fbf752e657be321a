"""``gf-cli batch [status] SUITE.toml [--local N | --ray ADDRESS]``: many jobs, on one machine or a Ray cluster."""

from __future__ import annotations

from pathlib import Path


def register(sub):
    p = sub.add_parser("batch", help="run a suite of jobs (simulate, render-dataset in chunks, reconstruct, evaluate, "
                                     "predict) N at a time here or as Ray tasks",
                       description="A suite (TOML, see gf_core/batch/suite.py and the README's scale-out section) "
                                   "lists gf-cli jobs, their dependencies and resources. Finished jobs are skipped "
                                   "on a re-run; a failed job is retried up to its retries. `gf-cli batch status "
                                   "SUITE.toml` says where each job stands.")
    p.add_argument("what", nargs="+", metavar="[status] SUITE.toml", help="the suite file (after 'status': only report)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--local", type=int, default=None, metavar="N", help="N jobs at a time on this machine (default 1)")
    where.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="run each job as a Ray task on this cluster ('auto': the one `ray start` made here; "
                            "needs pip install -e '.[cluster]')")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the suite's [batch] out)")
    p.set_defaults(func=run)


def run(args) -> int:
    from gf_core.batch import LocalExecutor, RayExecutor, load_suite, run_jobs, status, summary_table
    from gf_core.errors import InputError

    what = list(args.what)
    report = what[0] == "status"
    if report:
        what = what[1:]
    if len(what) != 1:
        raise InputError("batch", "give one suite file: gf-cli batch [status] SUITE.toml")
    jobs, out = load_suite(Path(what[0]), args.out)
    if report:
        rows = status(jobs, out)
        print(summary_table(rows))
        print(f"{sum(r['state'] == 'done' for r in rows)} of {len(rows)} jobs done in {out}")
        return 0
    if args.local is not None and args.local < 1:
        raise InputError("--local", f"must be at least 1, got {args.local}")
    ex = RayExecutor(args.ray) if args.ray else LocalExecutor(args.local or 1)
    rows = run_jobs(jobs, out, ex)
    print()
    print(summary_table(rows))
    bad = [r["job"] for r in rows if r["state"] not in ("done", "done earlier")]
    print(f"{len(rows) - len(bad)} of {len(rows)} jobs done" + (f"; not done: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0
