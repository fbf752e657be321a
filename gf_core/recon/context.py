"""What the loss terms see of a training run (``Context``), of one decoded time of a step
(``Frame``) and of the whole step (``Step``): the training views, the model, the particle
spacing and smoothing length, the run's random generator, and caches computed once per run
(silhouettes, floor points) or kept while they stay valid (neighbour lists)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from ..sph.neighbors import knn
from .initial import floor_known, walls_known


class Context:
    def __init__(self, cfg, views, *, device, rng: np.random.Generator, time_map):
        self.cfg = cfg
        self.views = views
        self.device = device
        self.rng = rng                  # the run's generator: every draw of a step comes from it, in order
        self.time_map = time_map
        self.seed = cfg.train.seed
        self.model = None               # set at initialisation (and replaced on resume or surgery)
        self.spacing = self.h = None
        self.box_source = None
        self.phase = 1
        self.version = 0                # bumped whenever the particle set changes (neighbour lists go stale)
        self._memo: dict = {}
        self.scratch: dict = {}         # per-term state kept between steps
        self._nbr: dict = {}
        self._cams: dict = {}

    def has(self, need: str) -> bool:
        """Whether what a term needs (``terms.base.NEEDS``) is there in this phase."""
        dec = self.model.decoder
        if need == "decoder":
            return self.phase > 1 and dec is not None
        if need == "residuals":
            return dec is not None and dec.knots is not None
        if need == "floor":
            return floor_known(self.box_source)
        if need == "guide":  # the simulated guide runs: a solver is set and the container is known (trainer.start_guide)
            return dec is not None and self.cfg.guide.solver != "none" and walls_known(self.box_source)
        raise KeyError(need)

    def memo(self, key, make: Callable[[], Any]):
        """``make()`` computed once per run for ``key``."""
        if key not in self._memo:
            self._memo[key] = make()
        return self._memo[key]

    def neighbours(self, key, means: torch.Tensor) -> torch.Tensor:
        """(N, K) neighbour indices of a frame's particles (up to ``density.k`` nearest within h), kept
        per frame ``key`` and rebuilt after ``density.refresh_every`` uses or when the particle set
        changed; gradients flow through the distances of the stored pairs."""
        ent = self._nbr.get(key)
        if ent is None or ent[1] != self.version or ent[2] >= self.cfg.density.refresh_every:
            idx, _ = knn(means.detach(), self.cfg.density.k, self.h, sorted=False)
            ent = [idx, self.version, 0]
            self._nbr[key] = ent
        ent[2] += 1
        return ent[0]

    def drop_neighbours(self) -> None:
        self._nbr.clear()

    def camera_tensors(self, i: int):
        """(world-to-camera (4, 4), intrinsics (4,)) of training image ``i`` on the device."""
        if i not in self._cams:
            self._cams[i] = self.views.cameras[i].to_torch(device=self.device, dtype=torch.float32)
        return self._cams[i]

    def frame_index(self, t: float) -> int:
        """The training frame (index into the views' unique times, the residuals' knots) nearest ``t``."""
        return int(np.argmin(np.abs(self.views.unique_times - t)))


@dataclass
class Frame:
    """One decoded time of a step: its particles and the training images drawn at it."""

    ctx: Context
    t: float
    key: Any                    # its neighbour lists' key (the time, or "canonical" before the decoder)
    params: dict                # what the renderer takes: means, scales, quats, opacities, sh
    images: list                # training image indices
    scratch: dict = field(default_factory=dict)
    _nbr: Any = None

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    def neighbours(self) -> torch.Tensor:
        """The frame's neighbour lists, fetched once per step."""
        if self._nbr is None:
            self._nbr = self.ctx.neighbours(self.key, self.means)
        return self._nbr


@dataclass
class Step:
    """A whole step: its frames, its rendered images batched per size, and the schedule's blur."""

    frames: list
    batches: list               # [(width, rendered (B, H, W, C), target (B, H, W, C))], one per image size
    n_images: int
    blur: float                 # the L1 term's blur, a fraction of the image width


__all__ = ["Context", "Frame", "Step"]
