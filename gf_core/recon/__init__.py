"""The reconstruction (paper Sec. 3-4.1): moving Gaussian particles from multiview images.

``config`` (the presets' keys, ``presets/*.toml``) -> ``trainer.Trainer``, which composes
``views`` (the training images), ``initial`` (the scene box and the carved start), ``model``
(canonical particles) and ``decoder`` (the time decoder, Eq. 4, and per-frame residuals),
``sampling`` (what a step draws), ``schedule`` (phases, weight ramps, learning rates), ``terms``
(the loss of Eq. 11 as a registry of terms), ``strategy`` (densify / prune) and ``checkpoint``.
"""

from .config import PRESETS, ReconConfig, make_config
from .trainer import ReconstructionError, Trainer, reconstruct

__all__ = ["ReconConfig", "make_config", "PRESETS", "Trainer", "reconstruct", "ReconstructionError"]
