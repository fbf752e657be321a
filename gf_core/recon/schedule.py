"""The three phases' schedule (paper Sec. 4.1.2) as pure functions of the configuration, the phase
and how far it has come: phase lengths, weight ramps, the time window, blur, learning rates.

Phases: without a time budget each ends when its smoothed image loss stops improving (``Plateau``);
its cap, a fraction of ``phases.iterations``, sets its schedule (ramps, time window, densification,
rate decay), and a phase still improving at its cap goes on at the cap's settings, for at most
``phases.limit_factor`` times its cap. With a time budget (``train.time_budget_s``) each runs for
its share of the seconds (``phases.time_fractions``), the last one to the end of the budget.

1. canonical frame only, 3DGS-style: lambda_d = 0, lambda_a and lambda_v at ``phases.phase1_reg``
   of their final values; canonical particles only (no decoder).
2. every frame: the decoder on (theta at lr 1e-2, Phi at 1e-4, the canonical particles at
   ``lr.canonical_dynamic`` of their phase-1 rates); lambda_d rises linearly to
   ``phases.phase2_density`` of its final value.
3. lambda_a, lambda_v and lambda_d rise linearly to their final values (Table 1), then hold.

A static scene (one time) has no decoder: phases 2 and 3 refine the canonical particles. Ramps
span the first ``phases.min_fraction`` of a phase's cap, and the plateau test only watches the
loss after them (and, in phase 2, once the time window is the whole clip), so every ramp completes
and the loss it compares comes from one set of weights and frames.
"""

from __future__ import annotations

import math

from .config import ReconConfig
from . import terms as registry


def shares(cfg: ReconConfig, fractions, static: bool) -> list:
    """The three phases' shares; a static scene has no dynamic phase, whose share goes half to the
    refinement phase."""
    fr = [float(f) for f in fractions]
    if static:
        fr = [fr[0], 0.5 * fr[1], fr[2] + 0.5 * fr[1]]
    return fr


def phase_cap(cfg: ReconConfig, phase: int, static: bool) -> int:
    """The iterations of ``phase``'s schedule: its share of ``phases.iterations``."""
    fr = shares(cfg, cfg.phases.fractions, static)
    return int(round(cfg.phases.iterations * fr[phase - 1] / sum(fr)))


def phase_limit(cfg: ReconConfig, phase: int, static: bool) -> int:
    """Without a time budget: the iteration at which ``phase`` ends even if its loss still improves."""
    return int(round(cfg.phases.limit_factor * phase_cap(cfg, phase, static)))


def phase_deadline(cfg: ReconConfig, phase: int, static: bool) -> float:
    """With a time budget: the wall-clock second by which ``phase`` must end (the budget split by
    ``phases.time_fractions``, else like the iterations; time a phase leaves unused goes to the
    next); inf without one. A phase-1 step renders one frame and skips the decoder, so it costs a
    fraction of a later one: its share of the seconds is smaller than its share of the steps."""
    budget = cfg.train.time_budget_s
    if budget <= 0:
        return math.inf
    if cfg.phases.time_fractions:
        fr = shares(cfg, cfg.phases.time_fractions, static)
        return budget * sum(fr[:phase]) / sum(fr)
    caps = [phase_cap(cfg, k, static) for k in (1, 2, 3)]
    return budget * sum(caps[:phase]) / max(sum(caps), 1)


def progress(cfg: ReconConfig, phase: int, phase_it: int, now: float, phase_t0: float, static: bool
             ) -> tuple[float, float]:
    """(progress of the current phase towards its end, progress of the whole run), each in [0, 1]:
    by iterations towards the phase caps, or, with a time budget, by seconds towards the phase's
    share of it."""
    budget = cfg.train.time_budget_s
    if budget > 0:  # the seconds alone: phases.iterations does not apply
        span = phase_deadline(cfg, phase, static) - phase_t0
        p, run = (now - phase_t0) / max(span, 1e-9), now / budget
    else:  # where the schedule stands: the phases before at their caps, this one up to its cap
        caps = [phase_cap(cfg, k, static) for k in (1, 2, 3)]
        cap = caps[phase - 1]
        p = phase_it / max(cap, 1)
        run = (sum(caps[:phase - 1]) + min(phase_it, cap)) / max(sum(caps), 1)
    return min(max(p, 0.0), 1.0), min(max(run, 0.0), 1.0)


def ramp(cfg: ReconConfig, phase_progress: float) -> float:
    """Where the weight ramps stand: 0 -> 1 over the first ``phases.min_fraction`` of a phase."""
    return min(1.0, phase_progress / max(cfg.phases.min_fraction, 1e-9))


def window_width(cfg: ReconConfig, phase: int, phase_progress: float) -> float:
    """Half-width (in tau) of the time window phase 2 draws its times from, widening from the
    canonical time to the whole clip over ``phases.time_curriculum`` of the phase; 1 = the whole clip."""
    cur = cfg.phases.time_curriculum
    return 1.0 if (phase != 2 or cur <= 0) else min(1.0, phase_progress / cur)


def ramps_done(cfg: ReconConfig, phase: int, phase_progress: float) -> bool:
    """The phase's ramps (and in phase 2 its time window) are complete: the plateau test may watch."""
    return ramp(cfg, phase_progress) >= 1.0 and (phase != 2 or phase_progress >= cfg.phases.time_curriculum)


def blur(cfg: ReconConfig, phase: int, phase_progress: float) -> float:
    """Coarse to fine (phase 2): the L1 term's blur, a fraction of the image width, shrinking from
    ``loss.blur_start`` to none as the time window widens."""
    return cfg.loss.blur_start * (1.0 - window_width(cfg, phase, phase_progress)) if phase == 2 else 0.0


def loss_weights(cfg: ReconConfig, phase: int, ramp_progress: float, iteration: int | None = None) -> dict:
    """Every ``[loss]`` weight in ``phase`` (1-3) at ramp progress ``ramp_progress`` in [0, 1]: a
    term's final weight, 0 outside the phases it acts in (``Term.phases``, or from the phase its
    ``Term.phase_key`` holds), ramped as its kind says
    (``Term.ramp``: Eq. 11's schedules of lambda_d and of lambda_a / lambda_v above). At
    ``iteration``, a term with an ``every_key`` k > 1 weighs k times as much at every k-th
    iteration and 0 between."""
    lo, ph = cfg.loss, cfg.phases
    r = ph.phase1_reg
    on = {"all": True, "dynamic": phase > 1, "residuals": phase >= ph.residuals_from}
    w = {}
    for t in registry.TERMS:
        for key in t.keys():
            base = getattr(lo, key)
            if not (phase >= getattr(lo, t.phase_key[0]) if t.phase_key else on[t.phases]):
                w[key] = 0.0
            elif t.ramp == "density":
                w[key] = 0.0 if phase == 1 else ph.phase2_density * base * ramp_progress if phase == 2 else \
                    base * (ph.phase2_density + (1 - ph.phase2_density) * ramp_progress)
            elif t.ramp == "regulariser":
                w[key] = r * base if phase < 3 else base * (r + (1 - r) * ramp_progress)
            else:
                w[key] = base
            k = getattr(lo, t.every_key[0]) if t.every_key else 1
            if k > 1 and iteration is not None:
                w[key] = w[key] * k if iteration % k == 0 else 0.0
    return w


def learning_rates(cfg: ReconConfig, base: dict, phase: int, run_progress: float, phase_progress: float,
                   frozen: bool) -> dict:
    """The rate of every parameter group (``base``: their phase-1 rates; 'mlp' is Phi's): the
    means decay to ``lr.means_final`` over the run; the canonical particles learn at
    ``lr.canonical_dynamic`` of their rates from phase 2 on; theta and Phi learn from phase 2 on,
    unless the decoder is frozen; the residuals learn from ``phases.residuals_from`` and decay over
    phase 3 to ``lr.residuals_final``."""
    lr = cfg.lr
    decay = lr.means_final ** run_progress
    res_decay = lr.residuals_final ** phase_progress if phase == 3 else 1.0
    f = 1.0 if phase == 1 else lr.canonical_dynamic
    out = {}
    for name, rate in base.items():
        if name in ("features", "mlp"):
            out[name] = rate if phase > 1 and not frozen else 0.0
        elif name.startswith("residual_"):
            out[name] = rate * res_decay if phase >= cfg.phases.residuals_from else 0.0
        else:
            out[name] = rate * f * (decay if name == "means" else 1.0)
    return out


def refine_stop(cfg: ReconConfig, phase: int, phase_it: int, phase_progress: float, static: bool) -> int:
    """The phase iteration at which densify/prune stops: refinement ends for the last
    (1 - densify.stop_fraction) of the phase's seconds (with a time budget) or of its cap."""
    if cfg.train.time_budget_s > 0:
        return phase_it + 1 if phase_progress < cfg.densify.stop_fraction else 0
    return int(cfg.densify.stop_fraction * phase_cap(cfg, phase, static))


def phase_end(cfg: ReconConfig, phase: int, phase_it: int, now: float, phase_progress: float, static: bool,
              plateau: "Plateau") -> str | None:
    """Why the current phase ends now, or None: with a time budget at its share of the seconds and
    nothing else (the iteration caps and the plateau test are for runs without one); without one at
    its plateau once its ramps are done, at the latest at its limit."""
    if cfg.train.time_budget_s > 0:
        return "its share of the time budget is used" if now >= phase_deadline(cfg, phase, static) else None
    cap, limit = phase_cap(cfg, phase, static), phase_limit(cfg, phase, static)
    if phase_it >= limit:
        return (f"its iteration cap ({cap}, phases.iterations x its fraction)" if limit <= cap else
                f"its iteration limit ({limit}, phases.limit_factor x its cap {cap}; the image loss still improved)")
    if ramps_done(cfg, phase, phase_progress) and plateau.reached(phase_it):
        return (f"plateau: the smoothed image loss improved less than {cfg.phases.plateau_tol:g} "
                f"over {cfg.phases.plateau_window} iterations")
    return None


class Plateau:
    """Smoothed-loss plateau test: the image loss (lambda_r L1 + lambda_s D-SSIM) is smoothed with an
    exponential moving average (time constant ``window / 8`` iterations); the phase has plateaued
    when the best smoothed value of the last ``window`` iterations is not ``tol`` (relative) below
    the best value before them."""

    def __init__(self, window: int, tol: float):
        self.window, self.tol = max(int(window), 1), tol
        self.alpha = min(1.0, 8.0 / self.window)
        self.ema = None
        self.history: list[tuple[int, float]] = []

    def update(self, it: int, value: float) -> None:
        if not math.isfinite(value):
            return
        self.ema = value if self.ema is None else (1 - self.alpha) * self.ema + self.alpha * value
        self.history.append((it, self.ema))

    def reached(self, it: int) -> bool:
        before = [v for i, v in self.history if i <= it - self.window]
        recent = [v for i, v in self.history if i > it - self.window]
        if not before or not recent:
            return False
        return min(recent) > min(before) * (1 - self.tol)

    def state(self) -> dict:
        return {"ema": self.ema, "history": self.history[-2000:]}

    def load(self, st: dict) -> None:
        self.ema = st["ema"]
        self.history = [tuple(x) for x in st["history"]]


__all__ = ["phase_cap", "phase_limit", "phase_deadline", "progress", "ramp", "window_width", "ramps_done", "blur",
           "loss_weights", "learning_rates", "phase_end", "Plateau"]
