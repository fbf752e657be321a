"""Named scene presets (SI units, gravity -z as in Blender).

Every preset fills its fluid shape with a cubic lattice aligned with the walls' lattice; the
spacing is 0.1 m / k for an integer k chosen from ``particles`` (or given), so the same scene
runs at 2k or 100k particles. particle radius = spacing / 2.

| scene            | domain (m)                 | fluid                                     | material |
|------------------|----------------------------|-------------------------------------------|----------|
| water_cube       | 0.8 x 0.8 x 0.8            | 0.3 m cube, bottom at z = 0.3             | water    |
| water_sphere     | 0.8 x 0.8 x 0.8            | sphere r = 0.18 m at z = 0.45             | water    |
| honey_cone       | 0.8 x 0.8 x 0.8            | cone apex down: z 0.25..0.55, r 0.2 top   | honey    |
| water_splash     | 0.6 x 0.6 x 0.7            | sphere r = 0.16 m at z = 0.5, 1.5 m/s down | water    |
| dam_break        | 1.0 x 0.1 x 0.6            | column a = 0.2 m wide, 2a high at x = 0   | water    |
| hydrostatic_tank | 0.2 x 0.2 x 0.4            | water at rest up to H = 0.2 m             | water    |

water: 1000 kg/m^3, XSPH 0.05, no extra viscosity. honey: 1420 kg/m^3, kinematic viscosity
0.05 m^2/s (about 70 Pa s: honey near 10 C) solved implicitly, XSPH 0.05. At 0.02 m^2/s the
honey cone's spread was set by the floor's friction, which depends on how far the bottom layer
sits from the wall particles (95th-percentile radius at 0.6 s: 0.33 m with extrapolated wall
pressure, 0.43 m with wall pressure unknowns, water 0.48 m); at 0.05 m^2/s the bulk viscosity
sets it (0.27 m with either wall model).

``hydrostatic_tank`` settles for 6 s before t = 0 (``Scene.settle``, ``common.settle``): a lattice
is not the packing of water at rest (its top layer collapses 0.5 s into the run), so the scene
starts from the packing the solver itself comes to rest in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .common import Domain

# Honey sticks to its container (no-slip viscosity at the walls); water slides (free-slip, the
# solvers' default): with free-slip walls the honey cone spreads almost as far as water.
MATERIALS = {
    "water": {"rest_density": 1000.0, "viscosity": 0.0, "xsph": 0.05},
    "honey": {"rest_density": 1420.0, "viscosity": 0.05, "xsph": 0.05, "viscosity_boundary": "no-slip"},
}


@dataclass
class Scene:
    name: str
    domain: Domain
    material: str
    inside: object          # callable (P, 3) numpy -> bool mask
    volume: float           # fluid volume, m^3 (for the particle count)
    fps: float = 60.0
    seconds: float = 1.0
    velocity: tuple = (0.0, 0.0, 0.0)
    settle: float = 0.0     # seconds of damped settling before t = 0 (``common.settle``)
    notes: str = ""
    material_params: dict = field(default_factory=dict)

    def __post_init__(self):
        self.material_params = dict(MATERIALS[self.material])


def _box(lo, hi):
    lo, hi = np.asarray(lo), np.asarray(hi)
    return lambda P: np.all((P >= lo) & (P <= hi), axis=1)


def _sphere(c, r):
    c = np.asarray(c)
    return lambda P: np.linalg.norm(P - c, axis=1) <= r


def _cone(apex, height, radius):
    apex = np.asarray(apex)

    def f(P):
        dz = P[:, 2] - apex[2]
        rad = np.linalg.norm(P[:, :2] - apex[:2], axis=1)
        return (dz >= 0) & (dz <= height) & (rad <= radius * dz / height)
    return f


def presets() -> dict[str, Scene]:
    cube = Domain((-0.4, -0.4, 0.0), (0.4, 0.4, 0.8))
    return {
        "water_cube": Scene("water_cube", cube, "water", _box((-0.15, -0.15, 0.3), (0.15, 0.15, 0.6)),
                            0.3 ** 3, notes="NeuroFluid-like WaterCube: a cube of water falls into a box"),
        "water_sphere": Scene("water_sphere", cube, "water", _sphere((0.0, 0.0, 0.45), 0.18),
                              4 / 3 * math.pi * 0.18 ** 3, notes="NeuroFluid-like WaterSphere"),
        "honey_cone": Scene("honey_cone", cube, "honey", _cone((0.0, 0.0, 0.25), 0.3, 0.2),
                            math.pi * 0.2 ** 2 * 0.3 / 3, notes="NeuroFluid-like HoneyCone"),
        "water_splash": Scene("water_splash", Domain((-0.3, -0.3, 0.0), (0.3, 0.3, 0.7)), "water",
                              _sphere((0.0, 0.0, 0.5), 0.16), 4 / 3 * math.pi * 0.16 ** 3, velocity=(0.0, 0.0, -1.5),
                              notes="a violent splash: a sphere thrown down into a closed tank (about 3 m/s at the "
                                    "impact), sheets up the walls and spray"),
        "dam_break": Scene("dam_break", Domain((0.0, 0.0, 0.0), (1.0, 0.1, 0.6)), "water",
                           _box((0.0, 0.0, 0.0), (0.2, 0.1, 0.4)), 0.2 * 0.1 * 0.4,
                           notes="Martin & Moyce 1952 column, a = 0.2 m, height 2a"),
        "hydrostatic_tank": Scene("hydrostatic_tank", Domain((0.0, 0.0, 0.0), (0.2, 0.2, 0.4)), "water",
                                  _box((0.0, 0.0, 0.0), (0.2, 0.2, 0.2)), 0.2 ** 3, seconds=2.0, settle=6.0,
                                  notes="water at rest, H = 0.2 m: must stay at rest"),
    }


SCENES = tuple(presets())


def spacing_for(scene: Scene, particles: int | None = None, spacing: float | None = None) -> float:
    if spacing is None:
        if particles is None:
            particles = 2000
        if particles < 1:
            raise InputError(scene.name, f"need at least 1 particle, got {particles}")
        spacing = (scene.volume / particles) ** (1 / 3)
    if not spacing > 0:
        raise InputError(scene.name, f"spacing must be positive, got {spacing}")
    k = max(1, round(0.1 / spacing))
    return 0.1 / k


def initial_state(name: str, *, particles: int | None = None, spacing: float | None = None):
    """(scene, positions (N, 3), velocities (N, 3), particle radius) for a preset."""
    table = presets()
    if name not in table:
        raise InputError("simulate", f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    sc = table[name]
    d = spacing_for(sc, particles, spacing)
    lo, hi = np.asarray(sc.domain.lo), np.asarray(sc.domain.hi)
    axes = [lo[a] + d / 2 + d * np.arange(int(round((hi[a] - lo[a]) / d))) for a in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    P = P[sc.inside(P)]
    V = np.tile(np.asarray(sc.velocity, np.float64), (P.shape[0], 1))
    return sc, P.astype(np.float32), V.astype(np.float32), d / 2
