"""The three-phase GaussFluids trainer (paper Sec. 4.1.2): composes the model (``model``,
``temporal``), the losses (``losses``), densify/prune (``strategy``) and the renderer.

Phases (without a time budget each ends when its smoothed image loss stops improving -- the
plateau test below; its cap, a fraction of ``phases.iterations``, sets its schedule (ramps, time
window, densification, rate decay), and a phase still improving at its cap goes on at the cap's
settings, for at most ``phases.limit_factor`` times its cap; with a time budget,
``train.time_budget_s``, each runs for its share of the seconds, ``phases.time_fractions``, and
the last one to the end of the budget, whatever the iteration count; the log and recon.h5's
metrics say why each phase ended):
1. canonical frame only, 3DGS-style: lambda_d = 0, lambda_a and lambda_v at 10% of their final
   values; canonical particles only (no decoder).
2. every frame: random (time, views) samples, the decoder on (theta at lr 1e-2, Phi at 1e-4, the
   canonical particles at a tenth of their phase-1 rates); lambda_d rises linearly to 10% of its
   final value.
3. lambda_a, lambda_v and lambda_d rise linearly to their final values (Table 1), then hold.
A static scene (one time) has no decoder: phases 2 and 3 refine the canonical particles.
Ramps span the first ``phases.min_fraction`` of a phase's cap, and the plateau test only watches
the loss after them (and, in phase 2, once the time window is the whole clip), so every ramp
completes and the loss it compares comes from one set of weights and frames.

Plateau test: the image loss (lambda_r L1 + lambda_s D-SSIM) is smoothed with an exponential
moving average (time constant ``plateau_window / 8`` iterations); the phase has plateaued when
the best smoothed value of the last ``plateau_window`` iterations is not ``plateau_tol``
(relative) below the best value before them.

Background and alpha: with ``loss.background = "random"`` (default) every step composites the
ground-truth RGBA over a random colour and renders over the same colour, so colour and alpha
are both fitted (a transparent pixel cannot be matched by dark particles); "black", "white" and
"dataset" (the dataset's own background) use a fixed colour. Without alpha, the images are used
as they are, against the dataset's background. The alpha masks also carve the starting particles
(``scene_init.carve``) and, with ``loss.hull > 0``, give a silhouette term that is not in the
paper: in every rendered view, the mean distance from each particle's projection to the mask
plus the mean distance from 256 random mask pixels to the nearest projection
(``losses.hull_distance``, ``losses.silhouette_coverage``). The image loss reaches a particle
only through the pixels it covers; this term reaches particles and uncovered fluid at any
distance, which large motions need (measured in BENCHMARKS.md, "Reconstruction").

A fluid on the floor (not in the paper; with alpha and a scene box from the dataset or config,
gravity along -z): views that look down at a spreading sheet cannot tell it from fluid held higher
up along their rays, and the particles of a splash stay in a mound over the middle of the tank
while the far side stays empty. The floor points that every view of a frame sees inside the fluid
(``_floor_samples``) mark where the fluid rests on the floor; ``loss.floor`` pulls the nearest
particle into any of them left without one (``losses.floor_coverage``), and ``loss.settle`` pulls
down the particles that hang over them with no particle below (``losses.settling``), through that
frame's position residual only, so that no pull reaches the frames where the fluid falls free.

Coarse to fine in time and space (phase 2): the times drawn widen from the canonical one to the
whole clip over ``phases.time_curriculum`` of the phase, and the L1 term compares images blurred
with a Gaussian of ``loss.blur_start`` x width that shrinks to none as the window widens. Once the
window is the whole clip (from phase ``phases.error_sampling_from``), ``phases.error_sampling`` of
the draws pick frames in proportion to their smoothed image error (the splash after an impact is
harder than the free fall before it).

Decoder residuals (``decoder.residuals``, not in the paper; ``gf_core/temporal.py``): per-particle
pose corrections at the training frames, trained from phase ``phases.residuals_from`` at the rates
of the canonical means (undecayed), log-scales and quaternions times ``lr.residuals``. They give
each frame's particles a direct path to the images that the shared MLP gives only slowly. With
``phases.freeze_decoder`` phase 3 trains only them and the canonical particles: theta and Phi keep
what phase 2 left, and their output at each frame is computed once (``Decoder.freeze``). Colour
residuals (``decoder.color_residuals``) and opacity residuals (``decoder.opacity_residuals``)
add the same per-frame correction to each particle's base colour (degree-0 SH) and logit opacity,
at the rates of ``lr.sh_dc`` and ``lr.logit_opacity`` times ``lr.residuals``: a rendered water
surface glints differently in every frame, and a particle of one look for the whole clip can show
that only by moving. ``lr.residuals_final`` lets all residual rates decay over phase 3.
The images cannot tell which particle is which inside the fluid, so residuals fitted frame by
frame may let particles trade places between frames unseen; ``loss.residual_motion`` penalises
each particle's residual change to the neighbouring frames (``losses.residual_change``) and
``loss.smooth`` its acceleration there (``losses.acceleration``).

Density loss (Eq. 5): neighbour lists (up to K = ``density.k`` nearest within h) come from the
grid search of ``gf_core.neighbors`` on the decoded positions of a frame, are kept per frame and
rebuilt after ``density.refresh_every`` uses or whenever the particle set changes; gradients
flow through the distances of the stored pairs. h = ``density.h_factor`` x particle spacing,
where spacing = (fluid volume / particle count)^(1/3) (volume from the carved hull, or the box);
the paper's h = 0.3 is in NeuroFluid's units, about 2-3 of its particle spacings.

Stability: a step whose loss or gradients are not finite is skipped (its gradients dropped) and
reported; ``train.max_bad_steps`` in a row stop the run with a ``ReconstructionError``.
Parameters are projected after every step (unit quaternions, bounded scales, positions in the
box), so no NaN or Inf reaches ``recon.h5``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import losses as L
from .errors import GFError, InputError
from .io import atomic_path, write_recon
from .metrics import particle_volume
from .model import Bounds, FluidModel
from .neighbors import knn
from .recon_config import ReconConfig, from_dict
from .render import render
from .scene_init import carve, floor_known, in_hull, mean_foreground_color, random_in_box, scene_box, spacing_for
from .strategy import DensifyPrune, ParticleOptimizer
from .temporal import Decoder, TimeMap

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = "gaussfluids.checkpoint"


class ReconstructionError(GFError):
    """The run cannot continue (non-finite steps, a resume that does not match, ...)."""


# ---- data ---------------------------------------------------------------------------------------------
@dataclass
class Images:
    """Decoded images of one split, on the training device."""

    images: list          # (H, W, C) float32
    alphas: list          # (H, W) or None
    cameras: list
    times: np.ndarray     # seconds
    view_ids: list
    background: torch.Tensor

    def __len__(self) -> int:
        return len(self.images)

    @property
    def unique_times(self) -> np.ndarray:
        return np.unique(self.times)

    def at_time(self, t: float) -> list[int]:
        if not hasattr(self, "_by_time"):
            self._by_time = {}
            for i, ti in enumerate(self.times):
                self._by_time.setdefault(round(float(ti), 9), []).append(i)
        return list(self._by_time.get(round(float(t), 9), []))


def load_images(ds, device, dtype=torch.float32) -> Images:
    imgs, alphas, cams, times, views = [], [], [], [], []
    for i in range(len(ds)):
        img, alpha = ds.load(i)
        if not np.all(np.isfinite(img)):
            raise InputError(ds.frames[i].file, "image contains NaN or infinite values")
        imgs.append(torch.as_tensor(img, dtype=dtype, device=device))
        alphas.append(None if alpha is None else torch.as_tensor(alpha, dtype=dtype, device=device))
        rec = ds.frames[i]
        cams.append(rec.camera)
        times.append(rec.time)
        views.append(rec.view_id)
    bg = torch.as_tensor(np.asarray(ds.background, np.float64)[:ds.channels], dtype=dtype, device=device)
    return Images(imgs, alphas, cams, np.asarray(times, np.float64), views, bg)


def mlp_low_precision(setting: str, device) -> bool:
    """Whether train.mlp_precision ``setting`` means bfloat16 on ``device``: "auto" only on a CPU
    whose oneDNN has native bf16 matrix products (there the MLP's products take about a third of
    the float32 time, BENCHMARKS.md); elsewhere (emulated bf16, GPUs) float32."""
    if setting != "auto":
        return setting == "bfloat16"
    if torch.device(device).type != "cpu":
        return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def dataset_fingerprint(ds) -> str:
    """A hash of what the images are (files, sizes, mtimes, cameras, times)."""
    h = hashlib.sha1()
    for f in ds.frames:
        st = os.stat(f.file)
        h.update(f"{f.file}|{st.st_size}|{st.st_mtime_ns}|{f.time}|{f.view_id}|{f.frame_index}".encode())
        h.update(np.asarray(f.camera.world_to_camera).tobytes())
    return h.hexdigest()[:16]


def composite(img: torch.Tensor, alpha: torch.Tensor | None, bg: torch.Tensor) -> torch.Tensor:
    if alpha is None:
        return img
    a = alpha[..., None]
    return img * a + bg.reshape(1, 1, -1) * (1 - a)


# ---- the schedule -------------------------------------------------------------------------------------
def loss_weights(cfg: ReconConfig, phase: int, ramp: float) -> dict:
    """The weights of Eq. 11 in ``phase`` (1-3) at ramp progress ``ramp`` in [0, 1]."""
    lo, ph = cfg.loss, cfg.phases
    w = {"rgb": lo.rgb, "ssim": lo.ssim, "opacity": lo.opacity, "color": lo.color, "hull": lo.hull,
         "floor": lo.floor, "settle": lo.settle, "motion": lo.motion if phase > 1 else 0.0,
         "smooth": lo.smooth if phase >= ph.residuals_from else 0.0,
         "residual_motion": lo.residual_motion if phase >= ph.residuals_from else 0.0}
    r = ph.phase1_reg
    if phase == 1:
        w.update(density=0.0, aniso=r * lo.aniso, volume=r * lo.volume)
    elif phase == 2:
        w.update(density=ph.phase2_density * lo.density * ramp, aniso=r * lo.aniso, volume=r * lo.volume)
    else:
        w.update(density=lo.density * (ph.phase2_density + (1 - ph.phase2_density) * ramp),
                 aniso=lo.aniso * (r + (1 - r) * ramp), volume=lo.volume * (r + (1 - r) * ramp))
    return w


class Plateau:
    """Smoothed-loss plateau test (see the module docstring)."""

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


# ---- checkpoints -----------------------------------------------------------------------------------------
_CHECKPOINT_KEYS = {  # key -> the types it may hold (the schema of Trainer.checkpoint_state)
    "fingerprint": (str,), "config": (dict,), "bounds": (dict,), "params": (dict,), "mlp": (dict, type(None)),
    "optimizer": (dict,), "plateau": (dict,), "iteration": (int,), "phase": (int,), "phase_it": (int,),
    "elapsed": (int, float), "spacing": (int, float), "h": (int, float), "volume": (int, float),
    "box_source": (str,), "init_source": (str,), "rng_torch": (torch.Tensor,), "rng_numpy": (str,)}
_CHECKPOINT_OPTIONAL = {"phase_t0": (int, float), "total_bad_steps": (int,), "frame_err": (list,),
                        "phase_ends": (list,), "time_map": (list,)}
_CHECKPOINT_PARAMS = ("means", "log_scales", "quats", "logit_opacity", "sh_dc", "sh_rest")


def check_checkpoint(st: dict, path) -> None:
    """The checkpoint's keys, types and per-particle tensors, one line naming the key otherwise."""
    def bad(what):
        raise InputError(path, f"damaged checkpoint: {what}; use --force to start afresh")

    for k, types in (*_CHECKPOINT_KEYS.items(), *_CHECKPOINT_OPTIONAL.items()):
        if k not in st:
            if k in _CHECKPOINT_OPTIONAL:
                continue
            bad(f"no {k!r}")
        v = st[k]
        if isinstance(v, bool) or not isinstance(v, types):
            bad(f"{k!r} is {type(v).__name__}, expected {' or '.join(t.__name__ for t in types)}")
        if isinstance(v, float) and not math.isfinite(v):
            bad(f"{k!r} is {v}")
    for k, nan_ok in (("frame_err", True), ("time_map", False)):  # frame_err: NaN = a frame not drawn yet
        if k in st and not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                               and (math.isfinite(x) or (nan_ok and math.isnan(x))) for x in st[k]):
            bad(f"{k!r} holds something other than {'numbers' if nan_ok else 'finite numbers'}")
    if not 1 <= st["phase"] <= 4 or st["iteration"] < 0 or st["phase_it"] < 0:
        bad(f"phase {st['phase']}, iteration {st['iteration']}, phase_it {st['phase_it']} out of range")
    params = st["params"]
    missing = [k for k in _CHECKPOINT_PARAMS if k not in params]
    if missing:
        bad(f"no per-particle {', '.join(missing)}")
    n = None
    for k, v in params.items():
        if not isinstance(v, torch.Tensor) or v.ndim < 1:
            bad(f"params.{k} is not a per-particle tensor")
        if n is None:
            n = v.shape[0]
        if v.shape[0] != n:
            bad(f"params.{k} has {v.shape[0]} rows, params.{next(iter(params))} {n}")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            bad(f"params.{k} has non-finite values")
    if st["mlp"] is not None and not all(isinstance(v, torch.Tensor) for v in st["mlp"].values()):
        bad("mlp holds something other than tensors")


# ---- the trainer -------------------------------------------------------------------------------------
class Trainer:
    def __init__(self, cfg: ReconConfig, train_ds, *, test_ds=None, out: Path, device="cpu", log=print,
                 progress=None):
        self.cfg = cfg
        self.out = Path(out)
        self.device = torch.device(device)
        self.log = log
        self.progress = progress
        self.train = load_images(train_ds, self.device)
        self.test = load_images(test_ds, self.device) if test_ds is not None and len(test_ds) else None
        self.channels = train_ds.channels
        self.fingerprint = dataset_fingerprint(train_ds)
        times = self.train.unique_times
        self.time_map = TimeMap(float(times.min()), float(times.max()))
        self.static = len(times) == 1
        self.dataset_meta = dict(train_ds.meta)
        self._sil, self._camt = {}, {}  # per training image: silhouette tensors, camera tensors
        self._floor = {}  # per training time: the wet floor (_floor_points; loss.floor, loss.settle)
        self._held_up = {}  # per training time: (its neighbour lists, losses.unsupported on them) for loss.settle
        self._train_ds = train_ds
        tau0 = cfg.decoder.canonical_time
        t_target = self.time_map.t_min + tau0 * self.time_map.duration
        self.t_canon = float(times[np.argmin(np.abs(times - t_target))])
        cfg.decoder.canonical_time = 0.0 if self.static else self.time_map.tau(self.t_canon)
        g = torch.Generator(device="cpu")
        g.manual_seed(cfg.train.seed)
        self.gen = g
        self.np_rng = np.random.default_rng(cfg.train.seed)
        self.iteration = 0
        self.phase = 1
        self.phase_it = 0
        self.phase_t0 = 0.0
        self.elapsed = 0.0
        self.bad_steps = 0
        self.total_bad_steps = 0
        self.nbr_cache: dict = {}
        self.frame_err = np.full(len(times), np.nan)  # smoothed image MSE per training frame
        self.version = 0
        self._phase_progress = 0.0
        self.phase_end_reasons = []  # why each phase ended (logged, and in recon.h5's metrics)
        self.model = None
        self.opt = None

    # ---- initialisation ------------------------------------------------------------------------------
    def initialise(self) -> None:
        cfg, mc = self.cfg, self.cfg.model
        canon = self.train.at_time(self.t_canon)
        lo, hi, src = scene_box(mc.scene_box, self._train_ds, [self.train.cameras[i] for i in canon], mc.floor)
        self.box_source = src
        if not floor_known(src):
            self.log("warning: no scene box and no floor are known (none given, none in the dataset), so the box is "
                     "guessed from the cameras: nothing keeps particles inside the real container or above its "
                     "floor (where no view can tell, they sink below it), and the floor and settle terms are off. "
                     "Give the container with --scene-box=X0,Y0,Z0,X1,Y1,Z1 or at least its floor with --floor Z "
                     "(metres, z up).")
        if cfg.loss.settle > 0 and not self.static and not cfg.decoder.residuals:
            self.log("loss.settle is off: it acts through the decoder residuals (decoder.residuals = false)")
        n0 = min(mc.init_particles, mc.max_particles)
        have_alpha = all(self.train.alphas[i] is not None for i in canon)
        if mc.init == "carve" and have_alpha:
            pts, volume = carve(lo, hi, [(self.train.cameras[i], self.train.alphas[i]) for i in canon], n0,
                                threshold=mc.carve_threshold, seed=cfg.train.seed)
            self.init_source = "carved"
        else:
            if mc.init == "carve":
                self.log("no alpha in the canonical frame's images: particles start uniform in the scene box")
            pts, volume = random_in_box(lo, hi, n0, cfg.train.seed), float(np.prod(hi - lo))
            self.init_source = "random"
        self.volume = volume
        self.spacing = spacing_for(volume, n0)
        self.h = cfg.density.h_factor * self.spacing
        color = mean_foreground_color([(self.train.images[i].cpu().numpy(),
                                        None if self.train.alphas[i] is None else self.train.alphas[i].cpu().numpy())
                                       for i in canon], self.channels)
        # a fluid particle's centre lies half a spacing from the wall it rests on, as in the simulators
        # (model.wall_inset): clamped to the box's faces instead, a sheet on the floor sits half a
        # spacing too low (docs/experiments/2026-12-02-wall-inset.md)
        bounds = Bounds.for_box(lo, hi, self.spacing, mc.wall_inset * self.spacing)
        self.model = FluidModel.from_points(
            torch.as_tensor(pts, dtype=torch.float32, device=self.device), radius=mc.init_scale * self.spacing,
            color=color, opacity=mc.init_opacity, sh_degree=mc.sh_degree, channels=self.channels, bounds=bounds,
            time_map=self.time_map, decoder_cfg=None if self.static else cfg.decoder, knots=self.knots(),
            seed=cfg.train.seed)
        self._make_optimizer()
        self._set_mlp_precision()
        self.log(f"start: {len(self.model)} particles ({self.init_source}) in the scene box from {src} "
                 f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()}; fluid volume {volume:.3g} m^3, "
                 f"spacing {self.spacing:.4g} m, h = {self.h:.4g} m; "
                 f"{'static scene (no decoder)' if self.static else f'{len(self.train.unique_times)} times'}")

    def _set_mlp_precision(self) -> None:
        """train.mlp_precision: the decoder's training passes in bfloat16 (``Decoder.mlp_dtype``)."""
        dec = self.model.decoder
        if dec is None:
            return
        low = mlp_low_precision(self.cfg.train.mlp_precision, self.device)
        dec.mlp_dtype = torch.bfloat16 if low else None
        if low:
            self.log(f"decoder MLP in bfloat16 in the training steps (train.mlp_precision = "
                     f"{self.cfg.train.mlp_precision}); recon.h5 and evaluation stay float32")

    def knots(self) -> list[float] | None:
        """The decoder residuals' knots: the training frames' tau (None without residuals)."""
        if self.static or not self.cfg.decoder.residuals:
            return None
        return [self.time_map.tau(t) for t in self.train.unique_times]

    def _make_optimizer(self) -> None:
        lr = self.cfg.lr
        lrs = {"means": lr.means * self.model.bounds.extent, "log_scales": lr.log_scales, "quats": lr.quats,
               "logit_opacity": lr.logit_opacity, "sh_dc": lr.sh_dc, "sh_rest": lr.sh_rest}
        if self.model.decoder is not None:
            lrs["features"] = lr.features
            for name in self.model.decoder.residuals():  # residual_dp/ds/dr/dc at the rates of means/log_scales/quats/sh_dc
                base = {"dp": "means", "ds": "log_scales", "dr": "quats", "dc": "sh_dc",
                        "do": "logit_opacity"}[name[len("residual_"):]]
                lrs[name] = lr.residuals * lrs[base]
        self.base_lrs = lrs
        betas = {name: (lr.residuals_beta1, 0.999) for name in lrs if name.startswith("residual_")}
        self.opt = ParticleOptimizer(self.model, lrs, mlp_lr=lr.mlp, betas=betas)
        dc = self.cfg.densify
        self.strategy = DensifyPrune(start=dc.start, every=dc.every, grad_threshold=dc.grad_threshold,
                                     clone_max_scale=dc.clone_max_scale, prune_opacity=dc.prune_opacity,
                                     prune_max_scale=dc.prune_max_scale, max_particles=self.cfg.model.max_particles)

    # ---- phases ------------------------------------------------------------------------------------------
    def _shares(self, fractions) -> list:
        fr = [float(f) for f in fractions]
        if self.static:  # no dynamic phase: its share goes to the refinement phase
            fr = [fr[0], 0.5 * fr[1], fr[2] + 0.5 * fr[1]]
        return fr

    def phase_cap(self, phase: int) -> int:
        ph = self.cfg.phases
        fr = self._shares(ph.fractions)
        return int(round(ph.iterations * fr[phase - 1] / sum(fr)))

    def phase_limit(self, phase: int) -> int:
        """Without a time budget: the iteration at which ``phase`` ends even if its loss still improves."""
        return int(round(self.cfg.phases.limit_factor * self.phase_cap(phase)))

    def ramp_len(self, phase: int) -> int:
        return max(1, int(self.cfg.phases.min_fraction * self.phase_cap(phase)))

    def phase_deadline(self, phase: int) -> float:
        """With a time budget: the wall-clock second by which ``phase`` must end (the budget split by
        ``phases.time_fractions``, else like the iterations; time a phase leaves unused goes to the
        next); inf without one. A phase-1 step renders one frame and skips the decoder, so it costs
        a fraction of a later one: its share of the seconds is smaller than its share of the steps."""
        budget = self.cfg.train.time_budget_s
        if budget <= 0:
            return math.inf
        if self.cfg.phases.time_fractions:
            fr = self._shares(self.cfg.phases.time_fractions)
            return budget * sum(fr[:phase]) / sum(fr)
        caps = [self.phase_cap(k) for k in (1, 2, 3)]
        return budget * sum(caps[:phase]) / max(sum(caps), 1)

    def schedule_progress(self, now: float) -> tuple[float, float]:
        """(progress of the current phase towards its end, progress of the whole run), each in
        [0, 1]: by iterations towards the phase caps, or, with a time budget, by seconds towards
        the phase's share of it."""
        budget = self.cfg.train.time_budget_s
        if budget > 0:  # the seconds alone: phases.iterations does not apply
            span = self.phase_deadline(self.phase) - self.phase_t0
            phase, run = (now - self.phase_t0) / max(span, 1e-9), now / budget
        else:  # where the schedule stands: the phases before at their caps, this one up to its cap
            caps = [self.phase_cap(k) for k in (1, 2, 3)]
            cap = caps[self.phase - 1]
            phase = self.phase_it / max(cap, 1)
            run = (sum(caps[:self.phase - 1]) + min(self.phase_it, cap)) / max(sum(caps), 1)
        return min(max(phase, 0.0), 1.0), min(max(run, 0.0), 1.0)

    def ramp(self, phase_progress: float) -> float:
        return min(1.0, phase_progress / max(self.cfg.phases.min_fraction, 1e-9))

    def window_width(self, phase_progress: float) -> float:
        """Half-width (in tau) of the time window phase 2 samples from; 1 = the whole clip."""
        cur = self.cfg.phases.time_curriculum
        return 1.0 if (self.phase != 2 or cur <= 0) else min(1.0, phase_progress / cur)

    def sample_times(self, phase_progress: float) -> list[float]:
        """The times of one step: the canonical one in phase 1 (and for a static scene); else
        ``train.times_per_step`` frames drawn uniformly from a window around the canonical time
        that widens to the whole clip over the first ``phases.time_curriculum`` of phase 2 (the
        decoder learns small motions before large ones)."""
        if self.phase == 1 or self.static:
            return [self.t_canon]
        times = self.train.unique_times
        tau = np.array([self.time_map.tau(t) for t in times])
        tau0 = self.cfg.decoder.canonical_time
        width = max(self.window_width(phase_progress), 2.0 / max(len(times) - 1, 1))
        pool = np.nonzero(np.abs(tau - tau0) <= width + 1e-9)[0]
        share = self.cfg.phases.error_sampling
        if share > 0 and self.phase >= self.cfg.phases.error_sampling_from and len(pool) == len(times) \
                and np.all(np.isfinite(self.frame_err)):
            # the hard frames (the splash) more often: a mixture of uniform and error-proportional draws
            err = np.maximum(self.frame_err, 1e-12)
            prob = (1 - share) / len(times) + share * err / err.sum()
            pick = self.np_rng.choice(len(times), size=self.cfg.train.times_per_step, replace=True, p=prob)
        else:
            pick = self.np_rng.choice(pool, size=self.cfg.train.times_per_step, replace=True)
        return [float(times[k]) for k in pick]

    FRAME_ERR_SMOOTHING = 0.2  # weight of the newest value in each frame's smoothed image error

    def _note_frame_errors(self, per_time, mses) -> None:
        """Smoothed mean squared image error of each training frame (for ``phases.error_sampling``)."""
        times = self.train.unique_times
        k = 0
        for t, idx in per_time:
            if not idx:
                continue
            m = float(np.mean(mses[k:k + len(idx)]))
            k += len(idx)
            f = int(np.argmin(np.abs(times - t)))
            a = self.FRAME_ERR_SMOOTHING
            self.frame_err[f] = m if not np.isfinite(self.frame_err[f]) else (1 - a) * self.frame_err[f] + a * m

    def _set_lrs(self, run_progress: float, phase_progress: float = 0.0) -> None:
        decay = self.cfg.lr.means_final ** run_progress
        # the residuals' rates decay over the last phase to lr.residuals_final (1 = constant)
        res_decay = self.cfg.lr.residuals_final ** phase_progress if self.phase == 3 else 1.0
        f = 1.0 if self.phase == 1 else self.cfg.lr.canonical_dynamic
        dec = self.model.decoder
        frozen = dec is not None and self.phase == 3 and self.cfg.phases.freeze_decoder
        if dec is not None:
            dec.freeze(frozen)  # theta and Phi get no gradient (phases.freeze_decoder)
        for name, lr in self.base_lrs.items():
            if name == "features":
                self.opt.set_lr(name, lr if self.phase > 1 and not frozen else 0.0)
            elif name.startswith("residual_"):
                on = self.phase >= self.cfg.phases.residuals_from
                self.opt.set_lr(name, lr * res_decay if on else 0.0)  # each frame gets a few hundred steps
            else:
                self.opt.set_lr(name, lr * f * (decay if name == "means" else 1.0))
        if dec is not None:
            self.opt.set_lr("mlp", self.cfg.lr.mlp if self.phase > 1 and not frozen else 0.0)

    # ---- one step ----------------------------------------------------------------------------------------
    def _neighbors(self, key, means: torch.Tensor):
        ent = self.nbr_cache.get(key)
        if ent is None or ent[1] != self.version or ent[2] >= self.cfg.density.refresh_every:
            idx, _ = knn(means.detach(), self.cfg.density.k, self.h, sorted=False)
            ent = [idx, self.version, 0]
            self.nbr_cache[key] = ent
        ent[2] += 1
        return ent[0]

    HULL_PIXELS = 256  # fluid pixels per view and step for the silhouette coverage term

    def _silhouette(self, i: int):
        """(distance to the silhouette (H, W), the fluid pixels' centres in a fixed random order
        with the first HULL_PIXELS repeated at the end (P + HULL_PIXELS, 2), P) of training image i.
        A step takes HULL_PIXELS consecutive rows from a random start: a slice, no host-to-device copy."""
        if i not in self._sil:
            a = self.train.alphas[i]
            rows, cols = torch.nonzero(a >= 0.5, as_tuple=True)
            pix = torch.stack([cols, rows], -1).to(a.dtype) + 0.5
            n = pix.shape[0]
            if n:
                order = torch.randperm(n, generator=torch.Generator().manual_seed(self.cfg.train.seed + i))
                pix = pix[order.to(pix.device)]
                pix = pix.repeat(-(-(n + self.HULL_PIXELS) // n), 1)[:n + self.HULL_PIXELS]
            self._sil[i] = (L.silhouette_distance(a), pix, n)
        return self._sil[i]

    def _hull_terms(self, items) -> torch.Tensor:
        """Sum over the step's images of hull_distance + silhouette_coverage (each image's
        HULL_PIXELS fluid pixels from its drawn start), batched over the images of one size: two
        calls per size instead of two per image (a step's op count is what a GPU step waits on)."""
        groups: dict = {}
        for item in items:
            cam = self.train.cameras[item[0]]
            groups.setdefault((cam.height, cam.width), []).append(item)
        total = 0.0
        for (_, width), grp in groups.items():
            means = torch.stack([m for _, m, _ in grp])
            cams = [self._cam_tensors(i) for i, _, _ in grp]
            vm, K = torch.stack([c[0] for c in cams]), torch.stack([c[1] for c in cams])
            sils = [self._silhouette(i) for i, _, _ in grp]
            total = total + L.hull_distance(means, torch.stack([sl[0] for sl in sils]), vm, K).sum()
            cov = [k for k, sl in enumerate(sils) if sl[2] > 0]  # an empty mask has no pixels to cover
            if cov:
                pix = torch.stack([sils[k][1][grp[k][2]:grp[k][2] + self.HULL_PIXELS] for k in cov])
                if len(cov) < len(grp):
                    means, vm, K = means[cov], vm[cov], K[cov]
                total = total + L.silhouette_coverage(means, pix, vm, K, width).sum()
        return total

    FLOOR_SAMPLES = 256  # floor points per decoded time and step for the floor term

    def _floor_points(self, t: float):
        """The wet floor of training time ``t``, computed once: (its points in a fixed random order,
        the first FLOOR_SAMPLES repeated at the end (P + FLOOR_SAMPLES, 3), P, the (nx, ny) bool grid
        of the floor cells that hold one), or None. The points: a grid at the particle spacing on
        the scene box's floor (lowest z, gravity along -z as in the simulators), half a spacing up,
        kept where every training view of that time that sees the point sees fluid (the alpha masks
        at model.carve_threshold). None where the frame's fluid does not reach the floor in every
        view (a falling drop) or a view has no alpha."""
        if t not in self._floor:
            idx = self.train.at_time(t)
            ent = None
            if idx and all(self.train.alphas[i] is not None for i in idx):
                lo, hi, g = np.asarray(self.model.bounds.lo), np.asarray(self.model.bounds.hi), self.spacing
                nx, ny = int(np.ceil((hi[0] - lo[0]) / g)), int(np.ceil((hi[1] - lo[1]) / g))
                I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
                P = np.stack([lo[0] + (I.ravel() + 0.5) * g, lo[1] + (J.ravel() + 0.5) * g,
                              np.full(I.size, lo[2] + 0.5 * g)], 1)
                keep = in_hull(P, [(self.train.cameras[i], self.train.alphas[i]) for i in idx],
                               self.cfg.model.carve_threshold)
                n = int(keep.sum())
                if n:
                    order = np.random.default_rng(self.cfg.train.seed).permutation(n)
                    pts = P[keep][order]
                    pts = np.concatenate([pts] * -(-(n + self.FLOOR_SAMPLES) // n))[:n + self.FLOOR_SAMPLES]
                    wet = torch.as_tensor(keep.reshape(nx, ny), device=self.device)
                    ent = (torch.as_tensor(pts, dtype=torch.float32, device=self.device), n, wet)
            self._floor[t] = ent
        return self._floor[t]

    def _floor_samples(self, t: float) -> torch.Tensor | None:
        """(M, 3) floor points of training time ``t`` for ``losses.floor_coverage``: all of them, or
        FLOOR_SAMPLES consecutive ones of the fixed random order from a random start (a slice, no
        host-to-device copy); None without a wet floor (``_floor_points``)."""
        ent = self._floor_points(t)
        if ent is None:
            return None
        pts, n, _ = ent
        if n <= self.FLOOR_SAMPLES:
            return pts[:n]
        s = int(self.np_rng.integers(n))
        return pts[s:s + self.FLOOR_SAMPLES]

    def _settle_term(self, t: float, means: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
        """losses.settling at training time ``t`` through that frame's position residual only (a
        frame's pull must not move the canonical particles or the decoder, and with them the frames
        where the fluid falls free), gated to the particles that hang unsupported over the wet part
        of the floor (a floor grid cell that holds one of ``_floor_points``). A frame whose fluid
        does not reach the floor in every view gets nothing."""
        ent = self._floor_points(t)
        if ent is None:
            return means.sum() * 0.0
        wet = ent[2]
        dec = self.model.decoder
        tau = torch.full((1,), self.time_map.tau(t), dtype=means.dtype, device=self.device)
        r = dec._residual_at(tau, "dp")[0][0]
        pos = means.detach() + (r - r.detach())
        lo = self.model.bounds.lo
        with torch.no_grad():
            q = torch.floor((means[:, :2].detach() - torch.as_tensor(lo[:2], dtype=means.dtype, device=self.device))
                            / self.spacing).long()
            inside = (q[:, 0] >= 0) & (q[:, 0] < wet.shape[0]) & (q[:, 1] >= 0) & (q[:, 1] < wet.shape[1])
            over = wet[q[:, 0].clamp(0, wet.shape[0] - 1), q[:, 1].clamp(0, wet.shape[1] - 1)] & inside
            # which particles hang unsupported: computed when the frame's neighbour lists are
            # (re)built (density.refresh_every) and reused with them, as slowly as they change
            held = self._held_up.get(t)
            if held is None or held[0] is not nbr:
                held = (nbr, L.unsupported(means.detach(), nbr, self.spacing, float(lo[2])))
                self._held_up[t] = held
            gate = over & held[1]
        return L.settling(pos, gate, float(lo[2]), self.spacing)

    def _frame_index(self, t: float) -> int:
        """The training frame (index into ``train.unique_times``, the residuals' knots) nearest ``t``."""
        return int(np.argmin(np.abs(self.train.unique_times - t)))

    def _smooth_term(self, t: float):
        """losses.acceleration at training time ``t`` from the decoded positions there and at the
        neighbouring training frames (None at the clip's first and last frame). The canonical
        positions cancel in the second difference; with a frozen decoder the MLP's part comes from
        its cache, so only the residuals get gradients."""
        times = self.train.unique_times
        j = self._frame_index(t)
        if j == 0 or j == len(times) - 1:
            return None
        taus = [self.time_map.tau(float(times[k])) for k in (j - 1, j, j + 1)]
        dp = self.model.decoder.forward_many(taus)["dp"]
        frame = 1.0 / (len(times) - 1)
        return L.acceleration(dp[0], dp[1], dp[2], taus[1] - taus[0], taus[2] - taus[1], frame, self.spacing)

    def _residual_motion_term(self, t: float) -> torch.Tensor:
        """losses.residual_change at training time ``t``: its frame's position residual against the
        neighbouring training frames' (one at the clip's ends). The knots are the training frames,
        so the residual there is the parameter itself (no interpolation)."""
        j = self._frame_index(t)
        r = self.model.decoder.residual_dp
        nbrs = [k for k in (j - 1, j + 1) if 0 <= k < r.shape[1]]
        return L.residual_change(r[:, j], r[:, nbrs], self.spacing)

    def _cam_tensors(self, i: int):
        if i not in self._camt:
            self._camt[i] = self.train.cameras[i].to_torch(device=self.device, dtype=torch.float32)
        return self._camt[i]

    def _background(self) -> torch.Tensor:
        mode = self.cfg.loss.background
        c = self.channels
        if mode == "random":  # from a bank drawn once: no host-to-device copy per step
            if getattr(self, "_bg_bank", None) is None:
                self._bg_bank = torch.rand(4096, c, generator=torch.Generator().manual_seed(self.cfg.train.seed)
                                           ).to(self.device)
            return self._bg_bank[int(self.np_rng.integers(4096))]
        if mode == "black":
            return torch.zeros(c, device=self.device)
        if mode == "white":
            return torch.ones(c, device=self.device)
        return self.train.background

    def step(self, phase_progress: float | None = None, run_progress: float | None = None) -> dict:
        """One optimiser step over ``train.times_per_step`` decoded times x ``train.views_per_step``
        views each. The loss of Eq. 11 is the mean image loss plus the regularisers (mean over
        the times); one device synchronisation per step (the finite check and the logged values
        travel together)."""
        cfg = self.cfg
        if phase_progress is None:
            phase_progress, run_progress = self.schedule_progress(self.elapsed)
        w = loss_weights(cfg, self.phase, self.ramp(phase_progress))
        self._set_lrs(run_progress, phase_progress)
        use_dec = self.phase > 1 and not self.static
        bg = self._background()
        times = self.sample_times(phase_progress)
        blur_frac = self.cfg.loss.blur_start * (1.0 - self.window_width(phase_progress)) if self.phase == 2 else 0.0
        img_loss, reg = 0.0, {}
        outs, mses = [], []
        n_img = 0
        per_time = []
        moved = []  # (tau, positions) for the least-motion term
        hull_items = []  # (training image, positions, first silhouette pixel) for the silhouette terms
        shots: dict = {}  # image size -> [(image number in this step, rendered colour, target)], for the image loss
        for t in times:
            idx = self.train.at_time(t)
            k = cfg.train.views_per_step
            if 0 < k < len(idx):
                idx = [idx[i] for i in self.np_rng.choice(len(idx), k, replace=False)]
            per_time.append((t, idx))
            n_img += len(idx)
        decoded = self.model.at_many([t if use_dec else None for t, _ in per_time]) if use_dec else \
            [self.model.at(None)] * len(per_time)
        for (t, idx), p in zip(per_time, decoded):
            if use_dec and w["motion"] > 0:
                moved.append((self.time_map.tau(float(t)), p["means"]))
            for i in idx:
                cam = self.train.cameras[i]
                out = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], cam, bg,
                             sh_degree=self.model.sh_degree)
                target = composite(self.train.images[i], self.train.alphas[i],
                                   bg if self.train.alphas[i] is not None else self.train.background)
                outs.append((out, cam))
                shots.setdefault((cam.height, cam.width), []).append((len(outs) - 1, out.color, target))
                if w["hull"] > 0 and self.train.alphas[i] is not None:
                    n_pix = self._silhouette(i)[2]
                    hull_items.append((i, p["means"], int(self.np_rng.integers(n_pix)) if n_pix else 0))
                    reg.setdefault("hull", 0.0)  # computed after the loop, for all images at once
            terms_t = {}
            dec = self.model.decoder
            settle = w["settle"] > 0 and use_dec and floor_known(self.box_source) and dec.knots is not None \
                and self.phase >= self.cfg.phases.residuals_from
            if w["density"] > 0 or settle:
                nbr = self._neighbors(float(t) if use_dec else "canonical", p["means"])
            if settle:
                terms_t["settle"] = w["settle"] * self._settle_term(float(t), p["means"], nbr)
            if w["density"] > 0:
                terms_t["density"] = w["density"] * L.density_uniformity(L.sph_density_knn(p["means"], nbr, self.h))
            if w["floor"] > 0 and floor_known(self.box_source):
                fs = self._floor_samples(float(t))
                if fs is not None:
                    terms_t["floor"] = w["floor"] * L.floor_coverage(p["means"], fs, self.spacing)
            if w["smooth"] > 0 and use_dec and dec.knots is not None:
                sm = self._smooth_term(float(t))
                if sm is not None:
                    terms_t["smooth"] = w["smooth"] * sm
            if w["residual_motion"] > 0 and use_dec and dec.knots is not None:
                terms_t["residual_motion"] = w["residual_motion"] * self._residual_motion_term(float(t))
            if w["volume"] > 0:
                terms_t["volume"] = w["volume"] * L.volume_consistency(p["scales"])
            if w["aniso"] > 0:
                terms_t["aniso"] = w["aniso"] * L.anisotropy(p["scales"])
            if w["opacity"] > 0:
                terms_t["opacity"] = w["opacity"] * L.opacity_consistency(p["opacities"])
            if w["color"] > 0:
                terms_t["color"] = w["color"] * L.color_consistency(p["sh"])
            for name, v in terms_t.items():
                reg[name] = reg.get(name, 0.0) + v / len(times)
        # the image loss (Eq. 11's L_rgb and L_d-ssim, each the mean over the step's images): one
        # batch per image size, so a step's op count does not grow with its images
        for (_, width), grp in shots.items():
            pred, target = torch.stack([c for _, c, _ in grp]), torch.stack([t for _, _, t in grp])
            li = 0.0
            if w["rgb"] > 0:
                sigma = blur_frac * width
                if sigma >= 0.5:  # coarse to fine (see sample_times / loss.blur_start)
                    li = li + w["rgb"] * L.l1(L.blur(pred, sigma), L.blur(target, sigma))
                else:
                    li = li + w["rgb"] * L.l1(pred, target)
            if w["ssim"] > 0:
                li = li + w["ssim"] * L.d_ssim(pred, target)
            img_loss = img_loss + li * (len(grp) / n_img)
            mses.append(((pred.detach() - target) ** 2).mean((1, 2, 3)))
        if hull_items:
            reg["hull"] = w["hull"] * self._hull_terms(hull_items) / n_img
        if len(moved) > 1:
            reg["motion"] = w["motion"] * L.least_motion([m for _, m in moved], [a for a, _ in moved], self.spacing)
        terms = {"image": img_loss, **reg}
        loss = sum(terms.values())
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
            self.opt.zero_grad()
            self.bad_steps += 1
            self.total_bad_steps += 1
            self.log(f"iteration {self.iteration}: non-finite loss or gradient, step skipped "
                     f"({self.bad_steps} in a row)")
            if self.bad_steps >= cfg.train.max_bad_steps:
                raise ReconstructionError(f"{self.bad_steps} consecutive non-finite steps at iteration "
                                          f"{self.iteration} (phase {self.phase}); the last checkpoint is "
                                          f"{self.out / CHECKPOINT}")
        term_vals = dict(zip(terms, vals[1:1 + len(terms)]))
        img_mse = [0.0] * len(outs)  # back in the order the images were drawn (per time, per view)
        for k, m in zip((k for grp in shots.values() for k, _, _ in grp), vals[1 + len(terms):]):
            img_mse[k] = m
        psnrs = [-10 * math.log10(m) if m > 0 else 99.0 for m in img_mse]
        if ok and use_dec:
            self._note_frame_errors(per_time, img_mse)
        return {"terms": term_vals, "weights": w, "loss": sum(term_vals.values()), "train_psnr": float(np.mean(psnrs)),
                "t": times[0], "finite": ok}

    # ---- refinement -----------------------------------------------------------------------------------
    def refine(self) -> dict:
        dc = self.cfg.densify
        if not dc.enabled or self.phase not in dc.phases:
            return {}
        if self.cfg.train.time_budget_s > 0:  # the last (1 - stop_fraction) of the phase's seconds: no refinement
            self.strategy.stop = self.phase_it + 1 if self._phase_progress < dc.stop_fraction else 0
        else:
            self.strategy.stop = int(dc.stop_fraction * self.phase_cap(self.phase))
        rep = self.strategy.refine(self.phase_it, self.model, self.opt, self.spacing, generator=self.gen)
        if rep and (rep["cloned"] or rep["split"] or rep["pruned"]):
            self.version += 1
        return rep

    # ---- evaluation -------------------------------------------------------------------------------------
    @torch.no_grad()
    def heldout_psnr(self) -> float | None:
        if self.test is None:
            return None
        times = self.test.unique_times
        pick = times[np.unique(np.linspace(0, len(times) - 1, min(self.cfg.train.eval_frames, len(times))).round()
                               .astype(int))]
        vals = []
        for t in pick:
            p = self.model.at(float(t) if self.phase > 1 else None)
            for i in self.test.at_time(float(t)):
                out = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], self.test.cameras[i],
                             self.test.background, sh_degree=self.model.sh_degree)
                target = composite(self.test.images[i], self.test.alphas[i], self.test.background)
                vals.append(L.psnr(out.color, target))
        return float(np.mean(vals)) if vals else None

    # ---- checkpoints ------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        m = self.model
        return {"format": CHECKPOINT_FORMAT, "version": 1, "config": self.cfg.to_dict(),
                "fingerprint": self.fingerprint, "iteration": self.iteration, "phase": self.phase,
                "phase_it": self.phase_it, "phase_t0": self.phase_t0, "elapsed": self.elapsed, "spacing": self.spacing, "h": self.h,
                "volume": self.volume, "box_source": self.box_source, "init_source": self.init_source,
                "bounds": m.bounds.to_dict(), "time_map": [self.time_map.t_min, self.time_map.t_max],
                "params": {k: v.detach().cpu() for k, v in m.per_particle().items()},
                "mlp": None if m.decoder is None else {k: v.cpu() for k, v in m.decoder.layers.state_dict().items()},
                "optimizer": self.opt.state_dict(), "plateau": self.plateau.state(),
                "rng_torch": self.gen.get_state(), "rng_numpy": json.dumps(self.np_rng.bit_generator.state),
                "total_bad_steps": self.total_bad_steps, "frame_err": self.frame_err.tolist(),
                "phase_ends": list(self.phase_end_reasons)}

    def save_checkpoint(self) -> Path:
        # neighbour lists are not stored: drop them here too, so that a resumed run rebuilds them
        # at the same iterations as an uninterrupted one
        self.nbr_cache.clear()
        path = self.out / CHECKPOINT
        with atomic_path(path) as tmp:
            torch.save(self.checkpoint_state(), tmp)
        return path

    def load_checkpoint(self, path: Path) -> None:
        try:
            st = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable checkpoint gets the same message
            raise InputError(path, f"cannot read the checkpoint ({type(e).__name__}: {e})") from None
        if not isinstance(st, dict) or st.get("format") != CHECKPOINT_FORMAT:
            raise InputError(path, "not a GaussFluids checkpoint")
        check_checkpoint(st, path)
        try:
            self._load_state(st, path)
        except GFError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as e:
            # what the schema check cannot see (an optimiser state or a layer of the wrong size)
            raise InputError(path, f"damaged checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:200]}); "
                                   "use --force to start afresh") from None

    def _load_state(self, st: dict, path: Path) -> None:
        if st["fingerprint"] != self.fingerprint:
            raise ReconstructionError(f"{path}: the checkpoint was made from other images than the dataset given "
                                      "(files, times or cameras differ); use --force to start afresh")
        saved = from_dict(st["config"])
        if saved.to_dict() != self.cfg.to_dict():
            diff = [f"{s}.{k}" for s, sec in self.cfg.to_dict().items() for k, v in sec.items()
                    if saved.to_dict()[s][k] != v]
            raise ReconstructionError(f"{path}: the checkpoint was made with another configuration "
                                      f"({', '.join(diff[:6])} differ); resume with the same options or use --force")
        b = st["bounds"]
        bounds = Bounds.from_dict(b)
        P = {k: v.to(self.device) for k, v in st["params"].items()}
        sh = torch.cat([P["sh_dc"], P["sh_rest"]], 1)
        dec = None
        if st["mlp"] is not None:
            dec = Decoder(P["means"].shape[0], self.cfg.decoder, knots=self.knots(), channels=self.channels,
                          device=self.device)
            dec.layers.load_state_dict(st["mlp"])
            dec.features = torch.nn.Parameter(P["features"])
            for name in dec.residuals():
                dec.set_residual(name, P[name])
        self.model = FluidModel(P["means"], P["log_scales"], P["quats"], P["logit_opacity"], sh, bounds=bounds,
                                time_map=self.time_map, decoder=dec)
        self.spacing, self.h, self.volume = st["spacing"], st["h"], st["volume"]
        self.box_source, self.init_source = st["box_source"], st["init_source"]
        self._make_optimizer()
        self._set_mlp_precision()
        self.opt.load_state_dict(st["optimizer"])
        self.iteration, self.phase, self.phase_it = st["iteration"], st["phase"], st["phase_it"]
        self.elapsed = st["elapsed"]
        self.phase_t0 = st.get("phase_t0", 0.0)
        self.total_bad_steps = st.get("total_bad_steps", 0)
        self.phase_end_reasons = list(st.get("phase_ends", []))
        if "frame_err" in st:
            self.frame_err = np.asarray(st["frame_err"], np.float64)
        self.plateau = Plateau(self.cfg.phases.plateau_window, self.cfg.phases.plateau_tol)
        self.plateau.load(st["plateau"])
        self.gen.set_state(st["rng_torch"])
        self.np_rng.bit_generator.state = json.loads(st["rng_numpy"])
        self.strategy.reset(len(self.model), self.device)

    # ---- the run ------------------------------------------------------------------------------------------
    def result_config(self) -> dict:
        return {"config": self.cfg.to_dict(), "spacing": self.spacing, "h": self.h,
                "fluid_volume": self.particle_volume(), "hull_volume": self.volume,
                "scene_box_source": self.box_source, "init": self.init_source, "dataset_fingerprint": self.fingerprint,
                "dataset": str(self._train_ds.root), "canonical_time_s": self.t_canon,
                "time_source": self.dataset_meta.get("time_source", "seconds"), "channels": self.channels,
                # the training frames' times: exports and the Blender extension sample these by default
                "frame_times_s": [float(t) for t in self.train.unique_times],
                "fps": float(self.dataset_meta["fps"]) if self.dataset_meta.get("fps") else None}

    def particle_volume(self) -> float:
        """The fluid volume the trained particles fill at the training frames (``metrics.particle_volume``,
        the density loss's kernel and h), what recon.h5 gives as ``fluid_volume`` (the particles' mass,
        and so every energy, and the spacing ``predict`` simulates at, follow from it); the volume the
        masks' hull held at the start (``self.volume``, the spacing and h of training) is ``hull_volume``."""
        times = [None] if self.static else [float(t) for t in self.train.unique_times]
        frames = []
        with torch.no_grad():
            for i in range(0, len(times), 8):  # eight frames per pass through the MLP
                frames += [p["means"] for p in self.model.at_many(times[i:i + 8])]
        return particle_volume(frames, self.h)

    def write_result(self, metrics: dict) -> Path:
        config = self.result_config()
        self.log(f"fluid volume {config['fluid_volume']:.3g} m^3 from the particles' SPH density (the masks' hull "
                 f"held {self.volume:.3g} m^3): the particles' mass and energies follow from it")
        r = self.model.to_recon(config=config, metrics=metrics)
        return write_recon(self.out / "recon.h5", r)

    def run(self, *, resume: bool = False) -> dict:
        from .io import folder_lock

        with folder_lock(self.out, "reconstruction"):
            return self._run(resume=resume)

    def trim_metrics(self) -> None:
        """metrics.jsonl as of the checkpoint: rows logged after it (a run killed between
        checkpoints) and a torn last line go, so the resumed run appends no duplicate."""
        mpath = self.out / "metrics.jsonl"
        if not mpath.exists():
            return
        keep = []
        for line in mpath.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                break  # a line torn by the kill, and nothing after it
            if int(row.get("iteration", 0)) > self.iteration:
                break
            keep.append(line)
        with atomic_path(mpath) as tmp:
            Path(tmp).write_text("".join(ln + "\n" for ln in keep))

    def _run(self, *, resume: bool = False) -> dict:
        ck = self.out / CHECKPOINT
        if resume and ck.exists():
            self.load_checkpoint(ck)
            self.trim_metrics()
            self.log(f"resumed from {ck}: iteration {self.iteration}, phase {self.phase}, {len(self.model)} particles")
        else:
            if resume:
                self.log(f"--resume: no checkpoint in {self.out}; starting afresh")
            self.initialise()
            self.plateau = Plateau(self.cfg.phases.plateau_window, self.cfg.phases.plateau_tol)
            (self.out / "metrics.jsonl").unlink(missing_ok=True)
        mpath = self.out / "metrics.jsonl"
        t_start = time.perf_counter() - self.elapsed
        acc = {"n": 0, "psnr": 0.0, "terms": {}, "loss": 0.0}
        last_test = None
        try:
            with open(mpath, "a") as mf:
                budget = self.cfg.train.time_budget_s
                while self.phase <= 3:
                    if budget > 0 and time.perf_counter() - t_start > budget:
                        now = time.perf_counter() - t_start
                        reason = f"the time budget of {budget:g} s is used"
                        self.log(f"phase {self.phase} ends at iteration {self.iteration} ({self.phase_it} iterations, "
                                 f"{now:.0f} s): {reason}; writing the result")
                        self.phase_end_reasons.append({"phase": self.phase, "iteration": self.iteration,
                                                       "wall_s": round(now, 3), "reason": reason})
                        break
                    cap = self.phase_cap(self.phase)
                    now = time.perf_counter() - t_start
                    phase_progress, run_progress = self.schedule_progress(now)
                    late = now >= self.phase_deadline(self.phase)
                    ramped = self.ramp(phase_progress) >= 1.0 and \
                        (self.phase != 2 or phase_progress >= self.cfg.phases.time_curriculum)
                    # with a time budget a phase ends at its share of the seconds and nothing else (the
                    # iteration caps and the plateau test are for runs without one)
                    if budget > 0:
                        reason = "its share of the time budget is used" if late else None
                    elif self.phase_it >= self.phase_limit(self.phase):
                        limit = self.phase_limit(self.phase)
                        reason = (f"its iteration cap ({cap}, phases.iterations x its fraction)" if limit <= cap else
                                  f"its iteration limit ({limit}, phases.limit_factor x its cap {cap}; "
                                  "the image loss still improved)")
                    elif ramped and self.plateau.reached(self.phase_it):
                        reason = (f"plateau: the smoothed image loss improved less than {self.cfg.phases.plateau_tol:g} "
                                  f"over {self.cfg.phases.plateau_window} iterations")
                    else:
                        reason = None
                    if reason is not None:
                        self.log(f"phase {self.phase} ends at iteration {self.iteration} ({self.phase_it} "
                                 f"iterations, {now:.0f} s): {reason}; {len(self.model)} particles")
                        self.phase_end_reasons.append({"phase": self.phase, "iteration": self.iteration,
                                                       "wall_s": round(now, 3), "reason": reason})
                        self.phase += 1
                        self.phase_it = 0
                        self.phase_t0 = now
                        self.plateau = Plateau(self.cfg.phases.plateau_window, self.cfg.phases.plateau_tol)
                        self.strategy.reset(len(self.model), self.device)
                        self.nbr_cache.clear()
                        self.elapsed = time.perf_counter() - t_start
                        self.save_checkpoint()
                        continue
                    self.elapsed = now
                    self._phase_progress = phase_progress
                    rec = self.step(phase_progress, run_progress)
                    self.iteration += 1
                    self.phase_it += 1
                    if rec["finite"]:
                        img = rec["terms"]["image"]
                        if ramped:
                            self.plateau.update(self.phase_it, img)
                        acc["n"] += 1
                        acc["psnr"] += rec["train_psnr"]
                        acc["loss"] += rec["loss"]
                        for k2, v in rec["terms"].items():
                            acc["terms"][k2] = acc["terms"].get(k2, 0.0) + v
                    ref = self.refine()
                    if ref:
                        self.nbr_cache.clear()
                    te = None
                    if self.test is not None and self.iteration % self.cfg.train.eval_every == 0:
                        te = last_test = self.heldout_psnr()
                    if self.iteration % self.cfg.train.log_every == 0 or te is not None:
                        n = max(acc["n"], 1)
                        line = {"wall_s": round(time.perf_counter() - t_start, 3), "iteration": self.iteration,
                                "phase": self.phase, "loss": acc["loss"] / n,
                                "terms": {k2: v / n for k2, v in acc["terms"].items()}, "weights": rec["weights"],
                                "train_psnr": acc["psnr"] / n, "particles": len(self.model),
                                "bad_steps": self.total_bad_steps}
                        if te is not None:
                            line["test_psnr"] = te
                        if ref:
                            line["refine"] = ref
                        mf.write(json.dumps(line) + "\n")
                        mf.flush()
                        if self.progress:
                            self.progress(line)
                        acc = {"n": 0, "psnr": 0.0, "terms": {}, "loss": 0.0}
                    if self.iteration % self.cfg.train.checkpoint_every == 0:
                        self.elapsed = time.perf_counter() - t_start
                        self.save_checkpoint()
        except KeyboardInterrupt:
            self.elapsed = time.perf_counter() - t_start
            path = self.save_checkpoint()
            self.log(f"interrupted at iteration {self.iteration}: checkpoint written to {path}; "
                     "--resume continues from it")
            raise
        self.elapsed = time.perf_counter() - t_start
        final_test = self.heldout_psnr()
        metrics = {"iterations": self.iteration, "wall_s": self.elapsed, "particles": len(self.model),
                   "train_psnr_last": acc["psnr"] / acc["n"] if acc["n"] else None,
                   "test_psnr": final_test if final_test is not None else last_test,
                   "bad_steps": self.total_bad_steps, "phase_ends": self.phase_end_reasons}
        self.save_checkpoint()
        path = self.write_result(metrics)
        self.log(f"wrote {path}: {len(self.model)} particles, {self.iteration} iterations in {self.elapsed:.1f} s"
                 + (f", held-out PSNR {final_test:.2f} dB" if final_test is not None else ""))
        return metrics


def reconstruct(dataset, out, cfg: ReconConfig, *, test_dataset=None, device="cpu", resume=False, log=print,
                progress=None) -> dict:
    """Run the three phases on ``dataset`` (a FluidDataset) and write ``out/recon.h5``."""
    tr = Trainer(cfg, dataset, test_ds=test_dataset, out=out, device=device, log=log, progress=progress)
    return tr.run(resume=resume)


__all__ = ["Trainer", "reconstruct", "ReconstructionError", "loss_weights", "Plateau", "CHECKPOINT"]
