"""What a loss term of Eq. 11 is to the trainer: its weight keys in ``[loss]`` with their
defaults, when it is active, what it needs, and how it is evaluated.

A term is evaluated ``per = "frame"`` (for every decoded time of a step, the mean over them
entering the loss) or ``per = "step"`` (once per step, over all its frames and images; what it
draws per frame it draws in ``prepare``). It is
never evaluated while all its weights are 0 or while something it needs is missing, so a scene
pays for nothing it does not use. Weights ramp as ``schedule.loss_weights`` says for its
``ramp`` kind; ``phases`` names the phases in which it acts, unless the term has a ``phase_key``:
a ``[loss]`` key (with its default) holding the first phase it acts in, 2 or 3, for the user to set.
A costly term may have an ``every_key``: a ``[loss]`` key (default 1) k such that the term is taken
at every k-th iteration only, at k times its weight (the same expected gradient for 1/k of the cost).
A term may have a ``guided_key``: a ``[loss]`` key (true / false) that, when true, makes the term act
only in runs whose simulated guide runs (``[guide]``, in a known container): need "guide".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

PHASES = ("all", "dynamic", "residuals")     # every phase; phases 2-3; from phases.residuals_from
RAMPS = (None, "density", "regulariser")     # Eq. 11's schedules of lambda_d and of lambda_a / lambda_v
NEEDS = ("decoder", "residuals", "floor", "guide")  # a decoded time; the decoder's per-frame residuals; a known
                                                   # floor; a simulated guide (recon/guide.py) that runs


@dataclass(frozen=True)
class Term:
    name: str                  # the name in metrics.jsonl's "terms"
    weights: tuple             # ((key in [loss], default weight), ...)
    per: str = "frame"         # "frame" or "step"
    phases: str = "all"
    phase_key: tuple | None = None  # (key in [loss], default first phase 2 or 3): overrides ``phases``
    every_key: tuple | None = None  # (key in [loss], default 1): taken every k-th iteration at k x its weight
    guided_key: tuple | None = None  # (key in [loss], default bool): true = also needs "guide"
    ramp: str | None = None
    needs: tuple = ()

    def keys(self) -> tuple:
        return tuple(k for k, _ in self.weights)

    def needs_in(self, loss) -> tuple:
        """What the term needs under the ``[loss]`` settings ``loss``: ``needs``, and "guide" when
        its ``guided_key`` is true."""
        return self.needs + (("guide",) if self.guided_key and getattr(loss, self.guided_key[0]) else ())

    def prepare(self, ctx, f, w: dict) -> None:
        """Called once a frame's images are rendered, before any term is evaluated: what a
        ``per = "step"`` term draws for each frame (in the order the frames come)."""

    def frame(self, ctx, f, w: dict) -> torch.Tensor | None:
        """The term at one decoded time ``f`` (``context.Frame``), weighted; None: nothing here."""
        raise NotImplementedError

    def step(self, ctx, s, w: dict) -> torch.Tensor | None:
        """The term over a whole step ``s`` (``context.Step``), weighted; None: nothing here."""
        raise NotImplementedError
