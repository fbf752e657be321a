"""The three-phase GaussFluids trainer (paper Sec. 4.1.2). It composes the parts and computes
nothing of its own: the training views (``views``), the starting particles (``initial``), what a
step draws (``sampling``), the schedule of phases, weights and rates (``schedule``), the loss terms
(``terms``, Eq. 11 and the terms beyond the paper), densify/prune (``strategy``) and checkpoints
(``checkpoint``). docs/method.md describes the method; each part's module its own piece.

A step decodes ``train.times_per_step`` times (the canonical one in phase 1), renders
``train.views_per_step`` training views of each, evaluates every active term (a weight of 0, or a
missing need, computes nothing) and takes one Adam step; one device synchronisation per step (the
finite check and the logged values travel together). A step whose loss or gradients are not finite
is skipped (its gradients dropped) and reported; ``train.max_bad_steps`` in a row stop the run with
a ``ReconstructionError``. Parameters are projected after every step (unit quaternions, bounded
scales, positions in the box), so no NaN or Inf reaches ``recon.h5``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch

from .. import native
from ..errors import ReconstructionError
from ..formats.hdf5 import output_lock, write_recon
from ..render import render
from . import checkpoint, schedule
from .config import ReconConfig
from .context import Context, Frame, Step
from .decoder import TimeMap, mlp_low_precision
from .guide import simulate_guide
from .initial import start
from .model import FluidModel
from .result import result_config
from .runlog import RunLog
from .sampling import Sampler
from .schedule import Plateau
from .strategy import DensifyPrune, make_optimizer
from . import terms as registry
from .views import dataset_fingerprint, heldout_psnr, load_views

CHECKPOINT = checkpoint.CHECKPOINT


class Trainer:
    def __init__(self, cfg: ReconConfig, train_ds, *, test_ds=None, out: Path, device="cpu", log=print,
                 progress=None):
        self.cfg, self.out, self.device = cfg, Path(out), torch.device(device)
        self.log, self.progress = log, progress
        self.dataset = train_ds
        self.views = load_views(train_ds, self.device)
        self.test = load_views(test_ds, self.device) if test_ds is not None and len(test_ds) else None
        self.fingerprint = dataset_fingerprint(train_ds)
        times = self.views.unique_times
        self.time_map = TimeMap(float(times.min()), float(times.max()))
        self.static = len(times) == 1
        t_target = self.time_map.t_min + cfg.decoder.canonical_time * self.time_map.duration
        self.t_canon = float(times[np.argmin(np.abs(times - t_target))])
        # the decoder's canonical time is the training frame nearest the asked one
        self.decoder_cfg = None if self.static else \
            dataclasses.replace(cfg.decoder, canonical_time=self.time_map.tau(self.t_canon))
        self.gen = torch.Generator(device="cpu").manual_seed(cfg.train.seed)
        rng = np.random.default_rng(cfg.train.seed)
        self.ctx = Context(cfg, self.views, device=self.device, rng=rng, time_map=self.time_map)
        self.sampler = Sampler(cfg, self.views, time_map=self.time_map, t_canon=self.t_canon, static=self.static,
                               rng=rng, device=self.device)
        self.iteration = self.phase = self.phase_it = 0
        self.phase, self.phase_t0, self.elapsed = 1, 0.0, 0.0
        self.bad_steps = self.total_bad_steps = 0
        self.phase_end_reasons = []  # why each phase ended (logged, and in recon.h5's metrics)
        self.guide_report = None     # [guide]: what the simulation did (recon.h5's metrics "guide")
        self.model = self.opt = None

    # ---- the parts ---------------------------------------------------------------------------------
    @property
    def model(self) -> FluidModel:
        return self.ctx.model

    @model.setter
    def model(self, m):
        if m is not None:
            m.wall_gradient = self.cfg.model.wall_gradient
        self.ctx.model = m

    def knots(self) -> list[float] | None:
        """The decoder residuals' knots: the training frames' tau (None without residuals)."""
        if self.static or not self.cfg.decoder.residuals:
            return None
        return [self.time_map.tau(t) for t in self.views.unique_times]

    def initialise(self) -> None:
        st = start(self.cfg, self.views, self.dataset, t_canon=self.t_canon, time_map=self.time_map,
                   decoder_cfg=self.decoder_cfg, knots=self.knots(), device=self.device, log=self.log)
        self.model, self.volume, self.box_source, self.init_source = st.model, st.volume, st.box_source, st.init_source
        self.ctx.spacing, self.ctx.h, self.ctx.box_source = st.spacing, st.h, st.box_source
        if self.cfg.loss.settle > 0 and not self.static and not self.cfg.decoder.residuals:
            self.log("loss.settle is off: it acts through the decoder residuals (decoder.residuals = false)")
        if not self.static and not self.ctx.has("guide"):
            for t in registry.TERMS:
                if "guide" in t.needs_in(self.cfg.loss) and any(getattr(self.cfg.loss, k) > 0 for k in t.keys()):
                    self.log(f"loss.{t.name} is off: it acts with the simulated guide only (loss.{t.guided_key[0]} = "
                             f"true), which needs guide.solver and a known container (the scene box is from "
                             f"{self.box_source}; give it with --scene-box=X0,Y0,Z0,X1,Y1,Z1)")
        self._make_optimizer()

    def _make_optimizer(self) -> None:
        self.opt, self.base_lrs = make_optimizer(self.cfg, self.model)
        self.strategy = DensifyPrune(self.cfg.densify, max_particles=self.cfg.model.max_particles)
        dec = self.model.decoder
        if dec is not None:  # train.mlp_precision: the decoder's training passes in bfloat16
            dec.mlp_dtype = torch.bfloat16 if mlp_low_precision(self.cfg.train.mlp_precision, self.device) else None
            if dec.mlp_dtype is not None:
                self.log(f"decoder MLP in bfloat16 in the training steps (train.mlp_precision = "
                         f"{self.cfg.train.mlp_precision}); recon.h5 and evaluation stay float32")

    def set_rates(self, run_progress: float, phase_progress: float) -> None:
        dec = self.model.decoder
        frozen = dec is not None and self.phase == 3 and self.cfg.phases.freeze_decoder
        if dec is not None:
            dec.freeze(frozen)  # theta and Phi get no gradient (phases.freeze_decoder)
        base = dict(self.base_lrs, **({"mlp": self.cfg.lr.mlp} if dec is not None else {}))
        for name, rate in schedule.learning_rates(self.cfg, base, self.phase, run_progress, phase_progress,
                                                  frozen).items():
            self.opt.set_lr(name, rate)

    # ---- one step -------------------------------------------------------------------------------------
    def step(self, phase_progress: float | None = None, run_progress: float | None = None) -> dict:
        """One optimiser step; the loss of Eq. 11 is the sum of the active terms, a per-frame term
        entering as its mean over the step's times. Without progress given, where the schedule
        stands at ``self.elapsed``."""
        cfg, ctx, views = self.cfg, self.ctx, self.views
        if phase_progress is None:
            phase_progress, run_progress = schedule.progress(cfg, self.phase, self.phase_it, self.elapsed,
                                                             self.phase_t0, self.static)
        ctx.phase = self.phase
        w = schedule.loss_weights(cfg, self.phase, schedule.ramp(cfg, phase_progress), self.iteration)
        self.set_rates(run_progress, phase_progress)
        use_dec = self.phase > 1 and not self.static
        active = [t for t in registry.TERMS if any(w[k] > 0 for k in t.keys())
                  and all(ctx.has(n) for n in t.needs_in(cfg.loss))]
        bg = self.sampler.background()
        times = self.sampler.times(self.phase, schedule.window_width(cfg, self.phase, phase_progress))
        per_time = [(t, self.sampler.view_indices(t)) for t in times]
        decoded = (self.model.at_many([t for t, _ in per_time], with_unclamped=True) if use_dec
                   else [self.model.at(None)] * len(per_time))
        values, frames, outs, shots = {}, [], [], {}
        for (t, idx), p in zip(per_time, decoded):
            f = Frame(ctx, float(t), float(t) if use_dec else "canonical", p, idx)
            for i in idx:
                cam = views.cameras[i]
                out = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], cam, bg,
                             sh_degree=self.model.sh_degree)
                outs.append((out, cam))
                shots.setdefault((cam.height, cam.width), []).append((len(outs) - 1, out.color, views.target(i, bg)))
            for term in active:
                term.prepare(ctx, f, w)
            for term in (t for t in active if t.per == "frame"):
                v = term.frame(ctx, f, w)
                if v is not None:
                    values[term.name] = values.get(term.name, 0.0) + v / len(times)
            frames.append(f)
        batches = [(width, torch.stack([c for _, c, _ in grp]), torch.stack([g for _, _, g in grp]))
                   for (_, width), grp in shots.items()]
        s = Step(frames, batches, len(outs), schedule.blur(cfg, self.phase, phase_progress))
        for term in (t for t in active if t.per == "step"):
            v = term.step(ctx, s, w)
            if v is not None:
                values[term.name] = v
        terms = {t.name: values[t.name] for t in registry.TERMS if t.name in values}
        loss = sum(terms.values())
        mses = [((pred.detach() - target) ** 2).mean((1, 2, 3)) for _, pred, target in batches]
        self.opt.zero_grad()
        loss.backward()
        grads = [q.grad for g in self.opt.opt.param_groups for q in g["params"] if q.grad is not None]
        gnorm = torch.stack(torch._foreach_norm(grads)).sum() if grads else loss.new_zeros(())
        vals = torch.cat([torch.stack([loss.detach() + gnorm] + [v.detach() for v in terms.values()])] + mses).tolist()
        ok = math.isfinite(vals[0])
        if ok:
            for out, cam in outs:
                self.strategy.step_post_backward(out.means2d, out.radii, cam.width, cam.height)
            self.opt.step()
            self.model.project_()
            self.bad_steps = 0
        else:
            self._skip_step()
        term_vals = dict(zip(terms, vals[1:1 + len(terms)]))
        img_mse = [0.0] * len(outs)  # back in the order the images were drawn (per time, per view)
        for k, m in zip((k for grp in shots.values() for k, _, _ in grp), vals[1 + len(terms):]):
            img_mse[k] = m
        if ok and use_dec:
            self.sampler.note_errors(per_time, img_mse)
        psnrs = [-10 * math.log10(m) if m > 0 else 99.0 for m in img_mse]
        return {"terms": term_vals, "weights": w, "loss": sum(term_vals.values()), "train_psnr": float(np.mean(psnrs)),
                "t": times[0], "finite": ok}

    def _skip_step(self) -> None:
        """A step whose loss or gradients are not finite: its gradients dropped, reported, and the
        run stopped after ``train.max_bad_steps`` in a row."""
        self.opt.zero_grad()
        self.bad_steps += 1
        self.total_bad_steps += 1
        self.log(f"iteration {self.iteration}: non-finite loss or gradient, step skipped ({self.bad_steps} in a row)")
        if self.bad_steps >= self.cfg.train.max_bad_steps:
            raise ReconstructionError(f"{self.bad_steps} consecutive non-finite steps at iteration {self.iteration} "
                                      f"(phase {self.phase}); the last checkpoint is {self.out / CHECKPOINT}")

    def refine(self, phase_progress: float) -> dict:
        """Densify and prune (``strategy``) until the schedule's stop (``schedule.refine_stop``)."""
        if not self.strategy.active(self.phase):
            return {}
        stop = schedule.refine_stop(self.cfg, self.phase, self.phase_it, phase_progress, self.static)
        rep = self.strategy.refine(self.phase_it, stop, self.model, self.opt, self.ctx.spacing, generator=self.gen)
        if rep and (rep["cloned"] or rep["split"] or rep["pruned"]):
            self.ctx.version += 1
        return rep

    def heldout_psnr(self) -> float | None:
        return heldout_psnr(self.model, self.test, decoded=self.phase > 1, frames=self.cfg.train.eval_frames)

    # ---- checkpoints and the result ---------------------------------------------------------------------
    def save_checkpoint(self) -> Path:
        # neighbour lists are not stored: drop them here too, so that a resumed run rebuilds them
        # at the same iterations as an uninterrupted one
        self.ctx.drop_neighbours()
        return checkpoint.write(self.out / CHECKPOINT, checkpoint.capture(self))

    def load_checkpoint(self, path: Path) -> None:
        st = checkpoint.read(path)
        with checkpoint.applying(path):
            checkpoint.restore(self, st, path)

    def write_result(self, metrics: dict) -> Path:
        config = result_config(self)
        self.log(f"fluid volume {config['fluid_volume']:.3g} m^3 from the particles' SPH density (the masks' hull "
                 f"held {self.volume:.3g} m^3): the particles' mass and energies follow from it")
        return write_recon(self.out / "recon.h5", self.model.to_recon(config=config, metrics=metrics))

    # ---- the run --------------------------------------------------------------------------------------
    def run(self, *, resume: bool = False) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        with output_lock(self.out, "reconstruction folder"):
            return self._run(resume=resume)

    def _end_phase(self, now: float, reason: str, *, last: bool = False) -> None:
        self.log(f"phase {self.phase} ends at iteration {self.iteration} ({self.phase_it} iterations, {now:.0f} s): "
                 f"{reason}; " + ("writing the result" if last else f"{len(self.model)} particles"))
        self.phase_end_reasons.append({"phase": self.phase, "iteration": self.iteration, "wall_s": round(now, 3),
                                       "reason": reason})

    def start_guide(self) -> None:
        """``[guide]``: the position residuals start where a simulation from the decoded particles
        carries them, and loss.residual_motion measures against that (recon/guide.py). Only in a
        known container: in a box guessed from the cameras the simulated fluid would spread to walls
        that are not there, and the residuals would follow it away from the images."""
        if not self.ctx.has("guide"):  # the caller checked the solver: the container is not known
            self.log(f"guide: not simulated: the container is not known (the scene box is a guess: "
                     f"{self.box_source}); give it with --scene-box=X0,Y0,Z0,X1,Y1,Z1 to use guide.solver")
            return
        guide, report = simulate_guide(self.model, self.views.unique_times, self.cfg.guide, spacing=self.ctx.spacing,
                                       log=self.log)
        with torch.no_grad():
            self.model.decoder.residual_dp.copy_(guide)
        self.model.set_per_particle("guide_dp", guide)
        self.guide_report = report

    def _next_phase(self, now: float, reason: str, t_start: float) -> None:
        self._end_phase(now, reason)
        self.phase, self.phase_it, self.phase_t0 = self.phase + 1, 0, now
        if self.phase == self.cfg.phases.residuals_from and self.cfg.guide.solver != "none" and not self.static:
            self.start_guide()
        self.plateau = Plateau(self.cfg.phases.plateau_window, self.cfg.phases.plateau_tol)
        self.strategy.reset(len(self.model), self.device)
        self.ctx.drop_neighbours()
        self.elapsed = time.perf_counter() - t_start
        self.save_checkpoint()

    def _run(self, *, resume: bool = False) -> dict:
        ck, runlog = self.out / CHECKPOINT, RunLog(self.out / "metrics.jsonl", self.progress)
        if resume and ck.exists():
            self.load_checkpoint(ck)
            runlog.trim(self.iteration)
            self.log(f"resumed from {ck}: iteration {self.iteration}, phase {self.phase}, {len(self.model)} particles")
        else:
            if resume:
                self.log(f"--resume: no checkpoint in {self.out}; starting afresh")
            self.initialise()
            self.plateau = Plateau(self.cfg.phases.plateau_window, self.cfg.phases.plateau_tol)
            runlog.restart()
        native.load()  # a first use compiles the extension (a minute or so): not part of the time budget
        t_start = time.perf_counter() - self.elapsed
        last_test, budget = None, self.cfg.train.time_budget_s
        try:
            with open(runlog.path, "a") as mf:
                while self.phase <= 3:
                    now = time.perf_counter() - t_start
                    if budget > 0 and now > budget:
                        self._end_phase(now, f"the time budget of {budget:g} s is used", last=True)
                        break
                    phase_progress, run_progress = schedule.progress(self.cfg, self.phase, self.phase_it, now,
                                                                     self.phase_t0, self.static)
                    reason = schedule.phase_end(self.cfg, self.phase, self.phase_it, now, phase_progress, self.static,
                                                self.plateau)
                    if reason is not None:
                        self._next_phase(now, reason, t_start)
                        continue
                    self.elapsed = now
                    rec = self.step(phase_progress, run_progress)
                    self.iteration += 1
                    self.phase_it += 1
                    if rec["finite"]:
                        if schedule.ramps_done(self.cfg, self.phase, phase_progress):
                            self.plateau.update(self.phase_it, rec["terms"]["image"])
                        runlog.add(rec)
                    ref = self.refine(phase_progress)
                    if ref:
                        self.ctx.drop_neighbours()
                    te = None
                    if self.test is not None and self.iteration % self.cfg.train.eval_every == 0:
                        te = last_test = self.heldout_psnr()
                    if self.iteration % self.cfg.train.log_every == 0 or te is not None:
                        runlog.write(mf, wall_s=time.perf_counter() - t_start, iteration=self.iteration,
                                     phase=self.phase, weights=rec["weights"], particles=len(self.model),
                                     bad_steps=self.total_bad_steps, test_psnr=te, refine=ref)
                    if self.iteration % self.cfg.train.checkpoint_every == 0:
                        self.elapsed = time.perf_counter() - t_start
                        self.save_checkpoint()
        except KeyboardInterrupt:
            self.elapsed = time.perf_counter() - t_start
            path = self.save_checkpoint()
            self.log(f"interrupted at iteration {self.iteration}: checkpoint written to {path}; --resume continues from it")
            raise
        self.elapsed = time.perf_counter() - t_start
        final_test = self.heldout_psnr()
        metrics = {"iterations": self.iteration, "wall_s": self.elapsed, "particles": len(self.model),
                   "train_psnr_last": runlog.train_psnr, "test_psnr": final_test if final_test is not None else last_test,
                   "bad_steps": self.total_bad_steps, "phase_ends": self.phase_end_reasons,
                   **({"guide": self.guide_report} if self.guide_report is not None else {})}
        self.save_checkpoint()
        path = self.write_result(metrics)
        self.log(f"wrote {path}: {len(self.model)} particles, {self.iteration} iterations in {self.elapsed:.1f} s"
                 + (f", held-out PSNR {final_test:.2f} dB" if final_test is not None else ""))
        return metrics


def reconstruct(dataset, out, cfg: ReconConfig, *, test_dataset=None, device="cpu", resume=False, log=print,
                progress=None) -> dict:
    """Run the three phases on ``dataset`` (a FluidDataset) and write ``out/recon.h5``."""
    return Trainer(cfg, dataset, test_ds=test_dataset, out=out, device=device, log=log, progress=progress).run(resume=resume)


__all__ = ["Trainer", "reconstruct", "ReconstructionError", "CHECKPOINT"]
