"""Configuration of ``gf-cli reconstruct``: nested dataclasses read from TOML presets
(``gf_core/recon/presets/{water,honey,smoke}.toml``, every key documented there) and user files.
``[loss]`` holds a weight per key of the registered loss terms (``terms/``), ``[decoder]`` is the
decoder's own config (``decoder.DecoderConfig``), ``[densify]`` the strategy's (``strategy.DensifyConfig``),
``[guide]`` the simulated motion prior's (``guide.GuideConfig``).

Precedence: built-in defaults < preset < ``--config FILE`` < command-line options. Unknown
sections or keys, and values of the wrong type, are errors that name the file and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..formats.toml_file import read_toml
from .decoder import DecoderConfig
from .guide import GuideConfig
from .strategy import DensifyConfig
from . import terms

PRESET_DIR = Path(__file__).parent / "presets"
PRESETS = ("water", "honey", "smoke")
WALL_GRADIENTS = ("none", "inward")  # model.wall_gradient (recon/model.py: FluidModel._bounded)


@dataclass
class ModelConfig:
    sh_degree: int = 1
    init: str = "carve"            # carve (alpha masks) | bright (the bright pixels as masks: smoke on black) | random
    init_particles: int = 8000
    max_particles: int = 16000
    init_opacity: float = 0.1
    init_scale: float = 0.5        # Gaussian std in particle spacings
    carve_threshold: float = 0.5   # alpha a carved point must see in every view that sees it
    bright_threshold: float = 0.05  # init = "bright": a pixel this far from the background is smoke
    scene_box: list = field(default_factory=list)  # [[x0, y0, z0], [x1, y1, z1]]; empty: dataset/cameras
    floor: list = field(default_factory=list)      # [z]: the floor's height alone (metres); empty: unknown
    floor_estimate: str = "silhouettes"  # without a known floor: "silhouettes" (recon/initial.py) | "none"
    wall_inset: float = 0.5        # particle centres stay this many particle spacings inside the scene box
    wall_gradient: str = "none"    # none | inward: the images' gradient reaches a coordinate held at a wall
                                   # when it points back inside (recon/model.py)


_LOSS_CLASSES: dict = {}


def loss_config_class():
    """[loss]: a weight per key of the registered terms (``terms.TERMS``), with its default (the
    paper's Table 1 for its terms), each a non-negative number (0 computes nothing); and how the
    image loss is taken; for a term with a ``phase_key``, the first phase (2 or 3) it acts in; for
    one with an ``every_key``, every how many iterations it is taken; for one with a ``guided_key``,
    whether it acts only with a running guide. Made from the registry, so a new term's key is a config
    key at once."""
    weights = tuple(terms.default_weights().items())
    starts = tuple(terms.phase_keys().items()) + tuple(terms.every_keys().items())
    flags = tuple(terms.guided_keys().items())
    if (weights, starts, flags) not in _LOSS_CLASSES:
        _LOSS_CLASSES[(weights, starts, flags)] = dataclasses.make_dataclass("LossConfig", [
            *[(k, float, field(default=v)) for k, v in weights],
            *[(k, int, field(default=v)) for k, v in starts],
            *[(k, bool, field(default=v)) for k, v in flags],
            ("background", str, field(default="random")),  # random | black | white | dataset (recon/sampling.py)
            ("blur_start", float, field(default=0.02)),    # phase 2 starts comparing images blurred by this x width
        ])
    return _LOSS_CLASSES[(weights, starts, flags)]


def LossConfig():  # noqa: N802 - reads as the dataclass it makes
    return loss_config_class()()


@dataclass
class DensityConfig:
    h_factor: float = 2.5          # h = h_factor x particle spacing
    k: int = 64                    # at most K nearest neighbours within h (paper: K = 64)
    refresh_every: int = 10        # neighbour lists rebuilt after this many uses


@dataclass
class LRConfig:
    means: float = 1.6e-4          # x box diagonal per step (3DGS: 1.6e-4 x scene extent)
    means_final: float = 0.01      # the means' learning rate decays to this fraction by the end
    log_scales: float = 5e-3
    quats: float = 1e-3
    logit_opacity: float = 5e-2
    sh_dc: float = 2.5e-3
    sh_rest: float = 1.25e-4
    features: float = 1e-2         # theta (paper: 1e-2)
    mlp: float = 1e-4              # Phi (paper: 1e-4)
    canonical_dynamic: float = 0.1  # factor on the canonical particles' rates in phases 2 and 3
    residuals: float = 1.0         # decoder residuals (decoder.residuals): factor on the means/log_scales/quats rates
    residuals_beta1: float = 0.9   # Adam's momentum for the residuals (a frame's get gradients only when it is drawn)
    residuals_final: float = 1.0   # the residuals' rates decay exponentially over phase 3 to this fraction


@dataclass
class PhaseConfig:
    iterations: int = 6000         # the schedule's length; phase caps are fractions of it
    fractions: list = field(default_factory=lambda: [0.2, 0.45, 0.35])
    time_fractions: list = field(default_factory=list)  # with a time budget: shares of it ([] = as fractions)
    min_fraction: float = 0.25     # a phase runs at least this fraction of its cap
    plateau_window: int = 400      # iterations
    plateau_tol: float = 0.005     # relative improvement of the smoothed image loss
    limit_factor: float = 3.0      # without a time budget: a phase still improving at its cap goes on, at most this x its cap
    phase1_reg: float = 0.1        # lambda_a, lambda_v in phase 1 as a fraction of the final ones
    phase2_density: float = 0.1    # lambda_d reaches this fraction by the end of phase 2
    time_curriculum: float = 0.5   # phase 2 samples times near the canonical one, widening to the clip over this fraction
    error_sampling: float = 0.0    # share of the time draws made in proportion to each frame's recent image error
    error_sampling_from: int = 2   # the phase (2 or 3) from which error_sampling applies
    residuals_from: int = 3        # the phase (2 or 3) from which the decoder residuals are trained
    freeze_decoder: bool = False   # phase 3 trains the canonical particles and residuals only (theta, Phi frozen)


@dataclass
class TrainConfig:
    seed: int = 0
    views_per_step: int = 2        # views rendered per decoded time (0: every training view)
    times_per_step: int = 3        # decoded times per step (phases 2-3)
    log_every: int = 25
    eval_every: int = 500          # held-out PSNR (when the dataset has test views)
    eval_frames: int = 6           # held-out frames evaluated during training
    checkpoint_every: int = 1000
    max_bad_steps: int = 20        # consecutive non-finite steps before the run stops
    time_budget_s: float = 0.0     # stop (and write the result) after this many wall-clock seconds; 0 = none
    mlp_precision: str = "auto"    # the decoder's hidden layers in training steps: auto, float32 or bfloat16


@dataclass
class ReconConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    loss: object = field(default_factory=LossConfig)
    density: DensityConfig = field(default_factory=DensityConfig)
    lr: LRConfig = field(default_factory=LRConfig)
    phases: PhaseConfig = field(default_factory=PhaseConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    guide: GuideConfig = field(default_factory=GuideConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def validate(self) -> "ReconConfig":
        where = "reconstruct config"
        check_ranges(self, where)
        m, lo, ph = self.model, self.loss, self.phases
        if m.sh_degree not in (0, 1, 2, 3):
            raise InputError(where, f"model.sh_degree must be 0-3, got {m.sh_degree}")
        if m.init not in ("carve", "bright", "random"):
            raise InputError(where, f"model.init must be 'carve', 'bright' or 'random', got {m.init!r}")
        if m.floor_estimate not in ("silhouettes", "none"):
            raise InputError(where, f"model.floor_estimate must be 'silhouettes' or 'none', got {m.floor_estimate!r}")
        if m.init_particles < 1 or m.max_particles < 1:
            raise InputError(where, "model.init_particles and model.max_particles must be >= 1")
        if not 0 < m.init_opacity < 1:
            raise InputError(where, f"model.init_opacity must be in (0, 1), got {m.init_opacity}")
        if m.scene_box:
            import numpy as np

            try:
                a = np.asarray(m.scene_box, np.float64)
            except (TypeError, ValueError):
                a = None
            if a is None or a.shape != (2, 3) or not np.all(np.isfinite(a)) or np.any(a[1] <= a[0]):
                raise InputError(where, f"model.scene_box must be [[x0, y0, z0], [x1, y1, z1]] with x1 > x0, "
                                        f"y1 > y0, z1 > z0 (metres), got {m.scene_box!r}")
        if m.floor and (len(m.floor) != 1 or isinstance(m.floor[0], bool) or not isinstance(m.floor[0], (int, float))
                        or m.floor[0] != m.floor[0] or abs(m.floor[0]) == float("inf")):
            raise InputError(where, f"model.floor must be [] or [z] with one finite height in metres, got {m.floor!r}")
        if m.floor and m.scene_box:
            raise InputError(where, "model.floor and model.scene_box exclude each other (the box's lowest z is its floor)")
        if m.wall_gradient not in WALL_GRADIENTS:
            raise InputError(where, f"model.wall_gradient must be none or inward, got {m.wall_gradient!r}")
        if not 0 <= m.wall_inset <= 2:
            raise InputError(where, f"model.wall_inset must be in [0, 2] particle spacings, got {m.wall_inset}")
        if lo.background not in ("random", "black", "white", "dataset"):
            raise InputError(where, f"loss.background must be random, black, white or dataset, got {lo.background!r}")
        for k in terms.weight_keys():
            v = getattr(lo, k)
            if not (isinstance(v, (int, float)) and v >= 0):
                raise InputError(where, f"loss.{k} must be a non-negative number, got {v!r}")
        for k in terms.phase_keys():
            if getattr(lo, k) not in (2, 3):
                raise InputError(where, f"loss.{k} must be 2 or 3 (the first phase the term acts in), got {getattr(lo, k)!r}")
        if not 0 <= lo.blur_start < 0.5:
            raise InputError(where, f"loss.blur_start must be in [0, 0.5), got {lo.blur_start}")
        if lo.rgb + lo.ssim <= 0:
            raise InputError(where, "loss.rgb + loss.ssim must be positive (nothing ties the particles to the images)")
        if ph.iterations < 1:
            raise InputError(where, f"phases.iterations must be >= 1, got {ph.iterations}")
        if len(ph.fractions) != 3 or any(f < 0 for f in ph.fractions) or sum(ph.fractions) <= 0:
            raise InputError(where, f"phases.fractions must be 3 non-negative numbers, got {ph.fractions}")
        if ph.time_fractions and (len(ph.time_fractions) != 3 or any(f < 0 for f in ph.time_fractions)
                                  or sum(ph.time_fractions) <= 0):
            raise InputError(where, "phases.time_fractions must be [] or 3 non-negative numbers, got "
                                    f"{ph.time_fractions}")
        if self.density.h_factor <= 0 or self.density.k < 1 or self.density.refresh_every < 1:
            raise InputError(where, "density.h_factor > 0, density.k >= 1 and density.refresh_every >= 1 required")
        if self.train.times_per_step < 1 or self.train.views_per_step < 0:
            raise InputError(where, "train.times_per_step must be >= 1 and train.views_per_step >= 0")
        if not 0 <= ph.time_curriculum <= 1:
            raise InputError(where, f"phases.time_curriculum must be in [0, 1], got {ph.time_curriculum}")
        if ph.residuals_from not in (2, 3):
            raise InputError(where, f"phases.residuals_from must be 2 or 3, got {ph.residuals_from}")
        if ph.freeze_decoder and not self.decoder.residuals:
            raise InputError(where, "phases.freeze_decoder needs decoder.residuals = true (a frozen decoder "
                                    "without residuals could not move the particles in phase 3; set it to false)")
        if not 0 < self.lr.residuals_final <= 1:
            raise InputError(where, f"lr.residuals_final must be in (0, 1], got {self.lr.residuals_final}")
        if not 0 <= self.lr.residuals_beta1 < 1:
            raise InputError(where, f"lr.residuals_beta1 must be in [0, 1), got {self.lr.residuals_beta1}")
        if not 0 <= ph.error_sampling <= 1:
            raise InputError(where, f"phases.error_sampling must be in [0, 1], got {ph.error_sampling}")
        if ph.error_sampling_from not in (2, 3):
            raise InputError(where, f"phases.error_sampling_from must be 2 or 3, got {ph.error_sampling_from}")
        if self.train.log_every < 1 or self.train.checkpoint_every < 1 or self.train.eval_every < 1:
            raise InputError(where, "train.log_every, eval_every and checkpoint_every must be >= 1")
        if self.train.mlp_precision not in ("auto", "float32", "bfloat16"):
            raise InputError(where, f"train.mlp_precision must be auto, float32 or bfloat16, got {self.train.mlp_precision!r}")
        self.guide.validate(where)
        if self.guide.solver != "none" and not self.decoder.residuals:
            raise InputError(where, "guide.solver needs decoder.residuals = true (the simulation is followed through "
                                    "the position residuals)")
        self.decoder.validate()
        return self


SECTIONS = {f.name: f.type for f in dataclasses.fields(ReconConfig)}

# The range of every numeric key (lists: of each element): (low, high, low excluded). Counts are bounded
# so that no value can ask for more memory than a workstation has before any work starts (the
# memory of the particles themselves: recon_config.training_bytes); rates and weights so that
# float32 arithmetic cannot overflow.
_W = (0.0, 1e6, False)   # a loss weight or a factor on one
_LR = (0.0, 10.0, False)  # a learning rate
RANGES = {
    "model.sh_degree": (0, 3, False), "model.init_particles": (1, 10**8, False),
    "model.max_particles": (1, 10**8, False), "model.init_opacity": (0.0, 1.0, True),
    "model.init_scale": (0.0, 100.0, True), "model.carve_threshold": (0.0, 1.0, False), "model.bright_threshold": (0.0, 1.0, False),
    "model.wall_inset": (0.0, 2.0, False),
    "decoder.feature_dim": (1, 4096, False), "decoder.hidden_layers": (1, 64, False),
    "decoder.hidden_width": (1, 8192, False), "decoder.n_freqs": (0, 20, False),
    "decoder.canonical_time": (0.0, 1.0, False),
    "loss.blur_start": (0.0, 0.5, False), **{f"loss.{k}": (2, 3, False) for k in terms.phase_keys()},
    **{f"loss.{k}": (1, 1000, False) for k in terms.every_keys()},
    "density.h_factor": (0.0, 10.0, True), "density.k": (1, 1024, False), "density.refresh_every": (1, 10**8, False),
    **{f"lr.{k}": _LR for k in ("means", "log_scales", "quats", "logit_opacity", "sh_dc", "sh_rest", "features", "mlp")},
    "lr.means_final": (0.0, 1.0, True), "lr.canonical_dynamic": (0.0, 100.0, False),
    "lr.residuals": (0.0, 1000.0, False), "lr.residuals_beta1": (0.0, 1.0, False),
    "lr.residuals_final": (0.0, 1.0, True),
    "phases.iterations": (1, 10**8, False), "phases.fractions": _W, "phases.time_fractions": _W,
    "phases.min_fraction": (0.0, 1.0, False), "phases.plateau_window": (1, 10**8, False),
    "phases.plateau_tol": (0.0, 1.0, False),
    "phases.limit_factor": (1.0, 100.0, False), "phases.phase1_reg": _W, "phases.phase2_density": _W,
    "phases.time_curriculum": (0.0, 1.0, False), "phases.error_sampling": (0.0, 1.0, False),
    "phases.error_sampling_from": (2, 3, False), "phases.residuals_from": (2, 3, False),
    "densify.phases": (1, 3, False), "densify.start": (0, 10**8, False), "densify.every": (1, 10**8, False),
    "densify.stop_fraction": (0.0, 1.0, False), "densify.grad_threshold": (0.0, 1e3, False),
    "densify.clone_max_scale": (0.0, 100.0, False), "densify.prune_opacity": (0.0, 1.0, False),
    "densify.prune_max_scale": (0.0, 1e3, True),
    "guide.start": (0.0, 1e6, False), "guide.viscosity": (0.0, 1e3, False),
    "guide.viscosity_fit": (0.0, 1e3, False), "guide.fit_frames": (1, 10**4, False),
    "train.seed": (0, 2**63 - 1, False), "train.views_per_step": (0, 10**4, False),
    "train.times_per_step": (1, 10**4, False), "train.log_every": (1, 10**8, False),
    "train.eval_every": (1, 10**8, False), "train.eval_frames": (0, 10**6, False),
    "train.checkpoint_every": (1, 10**8, False), "train.max_bad_steps": (1, 10**6, False),
    "train.time_budget_s": (0.0, 1e8, False),
}


def check_ranges(cfg: "ReconConfig", where: str) -> None:
    """Every numeric key (and every element of a numeric list) finite and inside RANGES."""
    import math

    for sec in SECTIONS:
        obj = getattr(cfg, sec)
        for f in dataclasses.fields(obj):
            key, v = f"{sec}.{f.name}", getattr(obj, f.name)
            values = v if isinstance(v, list) else [v]
            if key in ("model.scene_box", "model.floor"):
                continue  # checked with their own shapes below
            for x in values:
                if isinstance(x, bool) or not isinstance(x, (int, float)):
                    if isinstance(v, list) and key in RANGES:
                        raise InputError(where, f"{key} must be a list of numbers, got {v!r}")
                    continue
                if not math.isfinite(x):
                    raise InputError(where, f"{key} must be a finite number, got {x!r}")
                rng = RANGES.get(key) or (_W if sec == "loss" and f.name in terms.weight_keys() else None)
                if rng is None:
                    continue
                lo, hi, open_lo = rng
                if x > hi or x < lo or (open_lo and x == lo):
                    raise InputError(where, f"{key} must be in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {x!r}")


def training_bytes(cfg: "ReconConfig", frames: int = 1) -> int:
    """A lower bound of the memory a reconstruction holds per particle budget: canonical parameters,
    features and per-frame residuals, each with its gradient and Adam's two moments (float32)."""
    m, d = cfg.model, cfg.decoder
    per = 3 + 3 + 4 + 1 + 3 * (m.sh_degree + 1) ** 2 + d.feature_dim
    if d.residuals:
        per += frames * (10 + 3 * d.color_residuals + d.opacity_residuals)
    return int(m.max_particles) * per * 4 * 4


def _merge(cfg: ReconConfig, data: dict, where: str) -> None:
    for sec, values in data.items():
        if sec not in SECTIONS:
            raise InputError(where, f"unknown section [{sec}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, dict):
            raise InputError(where, f"[{sec}] must be a table of keys")
        obj = getattr(cfg, sec)
        known = {f.name: f for f in dataclasses.fields(obj)}
        for k, v in values.items():
            if k not in known:
                raise InputError(where, f"unknown key {sec}.{k} (known: {', '.join(known)})")
            cur = getattr(obj, k)
            if isinstance(cur, bool) and not isinstance(v, bool):
                raise InputError(where, f"{sec}.{k} must be true or false, got {v!r}")
            if isinstance(cur, (int, float)) and not isinstance(cur, bool):
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise InputError(where, f"{sec}.{k} must be a number, got {v!r}")
                if isinstance(cur, int) and not isinstance(v, int):
                    raise InputError(where, f"{sec}.{k} must be an integer, got {v!r}")
            if isinstance(cur, str) and not isinstance(v, str):
                raise InputError(where, f"{sec}.{k} must be a string, got {v!r}")
            if isinstance(cur, list) and not isinstance(v, list):
                raise InputError(where, f"{sec}.{k} must be a list, got {v!r}")
            setattr(obj, k, v)


def load_toml(path) -> dict:
    return read_toml(path, "config file")


def make_config(preset: str | None = "water", config_file=None, overrides: dict | None = None) -> ReconConfig:
    cfg = ReconConfig()
    if preset:
        if preset not in PRESETS:
            raise InputError("reconstruct", f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
        if preset != "water":  # honey and smoke are the water preset with some keys changed
            _merge(cfg, load_toml(PRESET_DIR / "water.toml"), str(PRESET_DIR / "water.toml"))
        p = PRESET_DIR / f"{preset}.toml"
        _merge(cfg, load_toml(p), str(p))
    if config_file:
        _merge(cfg, load_toml(config_file), str(config_file))
    if overrides:
        _merge(cfg, overrides, "command line")
    return cfg.validate()


def from_dict(d: dict, where: str = "checkpoint") -> ReconConfig:
    cfg = ReconConfig()
    _merge(cfg, d, where)
    return cfg.validate()


__all__ = ["ReconConfig", "make_config", "from_dict", "PRESETS", "PRESET_DIR", "load_toml"]
