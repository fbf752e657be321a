"""``RUN/metrics.jsonl``: one line per ``train.log_every`` iterations with the wall-clock seconds
beside the error (every loss term and weight, training and held-out PSNR, particles), the mean of
the steps since the line before. On resume the file is trimmed back to the checkpoint, so that no
row is duplicated or missing."""

from __future__ import annotations

import json
from pathlib import Path

from ..formats.hdf5 import atomic_path


class RunLog:
    def __init__(self, path: Path, progress=None):
        self.path, self.progress = Path(path), progress
        self._reset()

    def _reset(self) -> None:
        self.n, self.psnr, self.loss, self.terms = 0, 0.0, 0.0, {}

    def restart(self) -> None:
        """A run from the start: no earlier rows."""
        self.path.unlink(missing_ok=True)

    def trim(self, iteration: int) -> None:
        """Rows logged after ``iteration`` (a run killed between checkpoints) and a torn last line go."""
        if not self.path.exists():
            return
        keep = []
        for line in self.path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                break  # a line torn by the kill, and nothing after it
            if int(row.get("iteration", 0)) > iteration:
                break
            keep.append(line)
        with atomic_path(self.path) as tmp:
            Path(tmp).write_text("".join(ln + "\n" for ln in keep))

    def add(self, rec: dict) -> None:
        """One finite step's record (``Trainer.step``)."""
        self.n += 1
        self.psnr += rec["train_psnr"]
        self.loss += rec["loss"]
        for k, v in rec["terms"].items():
            self.terms[k] = self.terms.get(k, 0.0) + v

    @property
    def train_psnr(self) -> float | None:
        return self.psnr / self.n if self.n else None

    def write(self, f, *, wall_s: float, iteration: int, phase: int, weights: dict, particles: int,
              bad_steps: int, test_psnr=None, refine=None) -> None:
        n = max(self.n, 1)
        line = {"wall_s": round(wall_s, 3), "iteration": iteration, "phase": phase, "loss": self.loss / n,
                "terms": {k: v / n for k, v in self.terms.items()}, "weights": weights,
                "train_psnr": self.psnr / n, "particles": particles, "bad_steps": bad_steps}
        if test_psnr is not None:
            line["test_psnr"] = test_psnr
        if refine:
            line["refine"] = refine
        f.write(json.dumps(line) + "\n")
        f.flush()
        if self.progress:
            self.progress(line)
        self._reset()


__all__ = ["RunLog"]
