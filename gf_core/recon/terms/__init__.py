"""The loss of Eq. 11 as a registry of terms: ``TERMS`` lists every term once, in the order the
loss sums them. A term is a module of this package (its equation as a function, cited, and a
``Term`` object: its weight keys in ``[loss]`` with their defaults, when it acts, what it needs)
plus its line here; its weight is a key of the presets (``[loss]``), which ``config.LossConfig``
takes from this list. Weights of 0 compute nothing.

Per decoded time (the mean over the step's times): settle, gravity, container, density, floor, smooth,
residual_motion, volume, aniso, opacity, color. Per step: image (Eq. 11's L_rgb, L_d-ssim over all
the step's images), hull (all its masked images), motion, incompressible (across its times),
coherence (at one of its times)."""

from __future__ import annotations

from .aniso import ANISO
from .base import NEEDS, PHASES, RAMPS, Term
from .coherence import COHERENCE
from .color import COLOR
from .container import CONTAINER
from .density import DENSITY
from .floor import FLOOR
from .gravity import GRAVITY
from .hull import HULL
from .image import IMAGE
from .incompressible import INCOMPRESSIBLE
from .motion import MOTION
from .opacity import OPACITY
from .residual_motion import RESIDUAL_MOTION
from .settle import SETTLE
from .smooth import SMOOTH
from .volume import VOLUME

TERMS: tuple[Term, ...] = (
    IMAGE,
    HULL,
    SETTLE,
    GRAVITY,
    CONTAINER,
    DENSITY,
    FLOOR,
    SMOOTH,
    RESIDUAL_MOTION,
    COHERENCE,
    VOLUME,
    ANISO,
    OPACITY,
    COLOR,
    MOTION,
    INCOMPRESSIBLE,
)


def weight_keys(terms=None) -> tuple:
    """Every ``[loss]`` weight key, in the registry's order."""
    return tuple(k for t in (TERMS if terms is None else terms) for k in t.keys())


def default_weights(terms=None) -> dict:
    return {k: v for t in (TERMS if terms is None else terms) for k, v in t.weights}


def phase_keys(terms=None) -> dict:
    """Every ``[loss]`` key that sets the first phase of a term (``Term.phase_key``), with its default."""
    return dict(t.phase_key for t in (TERMS if terms is None else terms) if t.phase_key is not None)


def every_keys(terms=None) -> dict:
    """Every ``[loss]`` key that sets how often a term is taken (``Term.every_key``), with its default."""
    return dict(t.every_key for t in (TERMS if terms is None else terms) if t.every_key is not None)


def guided_keys(terms=None) -> dict:
    """Every ``[loss]`` key that makes a term act only with a running guide (``Term.guided_key``), with its default."""
    return dict(t.guided_key for t in (TERMS if terms is None else terms) if t.guided_key is not None)


def check_registry(terms=None) -> None:
    """Names and weight keys unique; ``per``, ``phases``, ``ramp`` and ``needs`` known."""
    terms = TERMS if terms is None else terms
    names = [t.name for t in terms]
    keys = list(weight_keys(terms)) + list(phase_keys(terms)) + list(every_keys(terms)) + list(guided_keys(terms))
    for what, seq in (("term name", names), ("weight key", keys)):
        dup = {x for x in seq if seq.count(x) > 1}
        if dup:
            raise ValueError(f"loss terms: {what} {sorted(dup)} registered twice")
    for t in terms:
        if t.per not in ("frame", "step") or t.phases not in PHASES or t.ramp not in RAMPS \
                or any(n not in NEEDS for n in t.needs):
            raise ValueError(f"loss term {t.name}: unknown per / phases / ramp / needs")
        if t.phase_key is not None and (len(t.phase_key) != 2 or t.phase_key[1] not in (2, 3)):
            raise ValueError(f"loss term {t.name}: phase_key must be (key, 2 or 3)")
        if t.every_key is not None and (len(t.every_key) != 2 or not isinstance(t.every_key[1], int) or t.every_key[1] < 1):
            raise ValueError(f"loss term {t.name}: every_key must be (key, an integer >= 1)")
        if t.guided_key is not None and (len(t.guided_key) != 2 or not isinstance(t.guided_key[1], bool)):
            raise ValueError(f"loss term {t.name}: guided_key must be (key, true or false)")


check_registry()

__all__ = ["TERMS", "Term", "weight_keys", "default_weights", "phase_keys", "every_keys", "guided_keys",
           "check_registry"]
