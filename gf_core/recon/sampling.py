"""What a training step draws, all from the run's one random generator and in one order (so that
a run is the same for the same seed, and a resumed run the same as an uninterrupted one): the
background colour, the decoded times and the views of each time.

Times: the canonical one in phase 1 (and for a static scene); else ``train.times_per_step`` frames
drawn uniformly from a window around the canonical time that widens to the whole clip over the
first ``phases.time_curriculum`` of phase 2 (the decoder learns small motions before large ones).
Once the window is the whole clip (from phase ``phases.error_sampling_from``),
``phases.error_sampling`` of the draws pick frames in proportion to their smoothed image error
(the splash after an impact is harder than the free fall before it).

Background: with ``loss.background = "random"`` every step composites the ground-truth RGBA over a
random colour and renders over the same colour, so colour and alpha are both fitted (a
transparent pixel cannot be matched by dark particles); "black", "white" and "dataset" use a
fixed colour.
"""

from __future__ import annotations

import numpy as np
import torch

SMOOTHING = 0.2  # weight of the newest value in each frame's smoothed image error
BANK = 4096      # random background colours drawn once (no host-to-device copy per step)


class Sampler:
    def __init__(self, cfg, views, *, time_map, t_canon: float, static: bool, rng: np.random.Generator, device):
        self.cfg, self.views, self.time_map = cfg, views, time_map
        self.t_canon, self.static, self.rng, self.device = t_canon, static, rng, device
        self.times_all = views.unique_times
        self.taus = np.array([time_map.tau(t) for t in self.times_all])
        self.tau0 = 0.0 if static else time_map.tau(t_canon)
        self.frame_err = np.full(len(self.times_all), np.nan)  # smoothed image MSE per training frame
        self._bank = None

    def background(self) -> torch.Tensor:
        mode, c = self.cfg.loss.background, self.views.channels
        if mode == "random":
            if self._bank is None:
                self._bank = torch.rand(BANK, c, generator=torch.Generator().manual_seed(self.cfg.train.seed)
                                        ).to(self.device)
            return self._bank[int(self.rng.integers(BANK))]
        if mode == "black":
            return torch.zeros(c, device=self.device)
        if mode == "white":
            return torch.ones(c, device=self.device)
        return self.views.background

    def times(self, phase: int, window: float) -> list[float]:
        """The step's decoded times; ``window``: the half-width in tau phase 2 draws from
        (``schedule.window_width``)."""
        if phase == 1 or self.static:
            return [self.t_canon]
        times = self.times_all
        width = max(window, 2.0 / max(len(times) - 1, 1))
        pool = np.nonzero(np.abs(self.taus - self.tau0) <= width + 1e-9)[0]
        share, k = self.cfg.phases.error_sampling, self.cfg.train.times_per_step
        if share > 0 and phase >= self.cfg.phases.error_sampling_from and len(pool) == len(times) \
                and np.all(np.isfinite(self.frame_err)):
            err = np.maximum(self.frame_err, 1e-12)
            prob = (1 - share) / len(times) + share * err / err.sum()
            pick = self.rng.choice(len(times), size=k, replace=True, p=prob)
        else:
            pick = self.rng.choice(pool, size=k, replace=True)
        return [float(times[j]) for j in pick]

    def view_indices(self, t: float) -> list[int]:
        """``train.views_per_step`` of the training images at time ``t`` (0: all of them)."""
        idx = self.views.at_time(t)
        k = self.cfg.train.views_per_step
        if 0 < k < len(idx):
            idx = [idx[i] for i in self.rng.choice(len(idx), k, replace=False)]
        return idx

    def note_errors(self, per_time, mses) -> None:
        """Each drawn frame's mean squared image error into its smoothed value."""
        k = 0
        for t, idx in per_time:
            if not idx:
                continue
            m = float(np.mean(mses[k:k + len(idx)]))
            k += len(idx)
            f = int(np.argmin(np.abs(self.times_all - t)))
            old = self.frame_err[f]
            self.frame_err[f] = m if not np.isfinite(old) else (1 - SMOOTHING) * old + SMOOTHING * m


__all__ = ["Sampler"]
