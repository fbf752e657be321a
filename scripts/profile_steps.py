"""Where a training step's time goes: milliseconds per step in each phase and the operators that
take the most device and host time (torch.profiler), for one dataset and config.

    python scripts/profile_steps.py DATASET [--device cuda] [--config FILE] [--particles N]
                                    [--steps K] [--out FILE.json]

Runs the trainer's own ``step`` (no time budget, no densify) for K steps in phase 1, 2 (window
over the whole clip) and 3, synchronising around each timed block, counts the ATen operators of
one step of phase 3 (or --profile-phase; on a GPU each is about one kernel launch), then profiles
K such steps. A diagnostic for choosing what to speed up; the figures that count are the
reconstruction benchmarks' (BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gf_core.data import load_dataset  # noqa: E402
from gf_core.recon.config import make_config  # noqa: E402
from gf_core.recon.schedule import Plateau  # noqa: E402
from gf_core.recon.trainer import Trainer  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--config", default=None)
    ap.add_argument("--particles", type=int, default=40000)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--profile-phase", type=int, default=3, choices=(1, 2, 3), help="the phase profiled")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    dev = torch.device(a.device)

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize()

    cfg = make_config("water", a.config, {"model": {"init_particles": a.particles, "max_particles": a.particles}})
    train = load_dataset(a.dataset)
    tr = Trainer(cfg, train, out=Path(tempfile.mkdtemp()), device=a.device, log=lambda *_: None)
    tr.initialise()
    tr.plateau = Plateau(10 ** 9, 0.0)
    rec = {"dataset": a.dataset, "device": torch.cuda.get_device_name(0) if dev.type == "cuda" else "cpu",
           "particles": len(tr.model), "times_per_step": cfg.train.times_per_step,
           "views_per_step": cfg.train.views_per_step, "ms_per_step": {}}
    for phase, prog in ((1, 0.5), (2, 0.95), (3, 0.5)):
        tr.phase = phase
        for _ in range(3):
            tr.step(prog, 0.5)
        sync()
        t0 = time.perf_counter()
        for _ in range(a.steps):
            tr.step(prog, 0.5)
        sync()
        rec["ms_per_step"][f"phase{phase}"] = 1e3 * (time.perf_counter() - t0) / a.steps
        print(f"phase {phase}: {rec['ms_per_step'][f'phase{phase}']:.1f} ms per step", flush=True)
    from torch.utils._python_dispatch import TorchDispatchMode

    class CountOps(TorchDispatchMode):  # every ATen operator a step dispatches (forward and backward)
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            CountOps.n += 1
            return func(*args, **(kwargs or {}))

    tr.phase = a.profile_phase
    with CountOps():
        tr.step(0.95 if a.profile_phase == 2 else 0.5, 0.5)
    rec["aten_ops_per_step"] = CountOps.n
    print(f"phase {a.profile_phase}: {CountOps.n} ATen operators per step", flush=True)
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    tr.phase = a.profile_phase
    with profile(activities=acts) as prof:
        for _ in range(a.steps):
            tr.step(0.95 if a.profile_phase == 2 else 0.5, 0.5)
        sync()
    ka = prof.key_averages()
    n = a.steps
    dev_attr = "self_device_time_total"
    by_dev = sorted([e for e in ka if getattr(e, dev_attr, 0) > 0], key=lambda e: -getattr(e, dev_attr))[:25]
    by_cpu = sorted(ka, key=lambda e: -e.self_cpu_time_total)[:25]
    rec["device_us_per_step"] = {e.key[:70]: round(getattr(e, dev_attr) / n, 1) for e in by_dev}
    rec["device_us_per_step_total"] = round(sum(getattr(e, dev_attr, 0) for e in ka) / n, 1)
    rec["host_us_per_step"] = {e.key[:70]: [round(e.self_cpu_time_total / n, 1), e.count // n] for e in by_cpu}
    rec["host_calls_per_step"] = sum(e.count for e in ka) // n
    print(f"device time per step {rec['device_us_per_step_total'] / 1e3:.1f} ms; "
          f"{rec['host_calls_per_step']} profiled host calls per step")
    print("top device time (us per step):")
    for k, v in rec["device_us_per_step"].items():
        print(f"  {v:9.1f}  {k}")
    print("top host self time (us per step, calls per step):")
    for k, (v, c) in rec["host_us_per_step"].items():
        print(f"  {v:9.1f} {c:5d}  {k}")
    if a.out:
        Path(a.out).write_text(json.dumps(rec, indent=1))


if __name__ == "__main__":
    main()
