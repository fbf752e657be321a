"""Many jobs at once: a suite of gf-cli commands with dependencies, run N at a time on this machine
or as Ray tasks on a cluster (``suite``: what to run; ``runner``: running it)."""

from .runner import LocalExecutor, RayExecutor, is_done, run_jobs, status, summary_table
from .suite import Job, expand, load_suite

__all__ = ["Job", "LocalExecutor", "RayExecutor", "expand", "is_done", "load_suite", "run_jobs", "status",
           "summary_table"]
