"""The solvers by name: one place maps ``--solver NAME`` to its class, its parameters and the
kernel its rest state is measured with. A new solver is a module of this package (the ``step`` /
state interface of ``dfsph.py`` and ``pbf.py``, its parameters checked in ``__post_init__``) and
one entry here."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..errors import InputError
from ..sph import kernels
from .dfsph import DFSPH, DFSPHParams
from .pbf import PBF, PBFParams


@dataclass(frozen=True)
class Solver:
    cls: type
    params: type                 # its parameter dataclass (``particle_radius``, material, settings)
    kernel: Callable             # W(r, h) of its density, for the rest state of given particles


SOLVERS: dict[str, Solver] = {
    "dfsph": Solver(DFSPH, DFSPHParams, kernels.WENDLAND.W),   # divergence-free SPH (Bender & Koschier 2015)
    "pbf": Solver(PBF, PBFParams, kernels.poly6),               # position-based fluids (Macklin & Mueller 2013)
}


def solver(name: str, where: str = "--solver") -> Solver:
    if name not in SOLVERS:
        raise InputError(where, f"unknown solver {name!r}; choose from {', '.join(SOLVERS)}")
    return SOLVERS[name]


def make_solver(name: str, radius: float, domain, material: dict, *, device="cpu", **overrides):
    """Solver ``name`` for particles of ``radius`` in ``domain``, with the ``material``
    parameters and any parameter ``overrides``."""
    s = solver(name, "simulate")
    return s.cls(s.params(particle_radius=radius, **{**material, **overrides}), domain, device=device)


__all__ = ["SOLVERS", "Solver", "solver", "make_solver"]
