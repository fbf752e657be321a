"""Editing a reconstructed fluid before simulating on (paper Sec. 4.3.5, Fig. 10): particles removed
(a fraction, a box, a sphere), moved, or added as a lattice block that takes the appearance of its
nearest reconstructed particles. Each edit returns a new ``predict.State`` and records itself in
``State.edits``; ``predict.keep_rest_state`` before editing keeps the particles' mass."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from ..errors import InputError
from .predict import State


def remove_fraction(s: State, fraction: float, seed: int = 0) -> State:
    """Remove a uniformly random ``fraction`` of the particles."""
    if not 0 <= fraction < 1:
        raise InputError("--remove-fraction", f"must be in [0, 1), got {fraction}")
    rng = np.random.default_rng(seed)
    n_remove = int(round(fraction * len(s)))
    keep = np.sort(rng.permutation(len(s))[n_remove:])
    return s.take(keep, {"remove_fraction": fraction, "seed": seed, "removed": n_remove})


def remove_box(s: State, lo, hi) -> State:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    inside = np.all((s.positions >= lo) & (s.positions <= hi), axis=1)
    return s.take(~inside, {"remove_box": [lo.tolist(), hi.tolist()], "removed": int(inside.sum())})


def remove_sphere(s: State, center, radius: float) -> State:
    c = np.asarray(center, np.float64)
    inside = np.linalg.norm(s.positions - c, axis=1) <= radius
    return s.take(~inside, {"remove_sphere": [c.tolist(), float(radius)], "removed": int(inside.sum())})


def translate(s: State, offset) -> State:
    """Move every particle by ``offset`` metres (kept inside the domain by the simulator)."""
    d = np.asarray(offset, np.float64)
    return replace(s, positions=s.positions + d, edits=s.edits + [{"translate": d.tolist()}])


def add_box(s: State, lo, hi, spacing: float, velocity=(0.0, 0.0, 0.0)) -> State:
    """Fill the box [lo, hi] with a lattice of ``spacing`` (the existing particles' spacing),
    leaving out lattice points closer than one spacing to an existing particle; each new particle
    takes the appearance of its nearest existing one and starts with ``velocity``."""
    from ..eval.metrics import nearest_distance

    if len(s) == 0:
        raise InputError("--add-box", "there is no particle left to take an appearance from")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    from ..limits import PARTICLE_BYTES, require_memory

    count = float(np.prod(np.maximum(hi - lo, 0.0) / spacing))
    require_memory("--add-box", f"{count:.3g} lattice points at the particles' spacing {spacing:.4g} m "
                                "(and their simulation)", count * PARTICLE_BYTES)
    axes = [np.arange(lo[k] + 0.5 * spacing, hi[k], spacing) for k in range(3)]
    if any(a.size == 0 for a in axes):
        raise InputError("--add-box", f"the box {lo.tolist()}..{hi.tolist()} holds no lattice point at spacing "
                                      f"{spacing:.4g} m")
    p = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d = nearest_distance(torch.as_tensor(p), torch.as_tensor(s.positions), 2 * spacing).numpy()
    p = p[d >= spacing]
    if p.shape[0] == 0:
        raise InputError("--add-box", "every lattice point of the box is already occupied by fluid")
    src_index = s.source_index[nearest_index(p, s.positions)]
    v = np.broadcast_to(np.asarray(velocity, np.float64), p.shape)
    return replace(s, positions=np.concatenate([s.positions, p]), velocities=np.concatenate([s.velocities, v]),
                   source_index=np.concatenate([s.source_index, src_index]),
                   edits=s.edits + [{"add_box": [lo.tolist(), hi.tolist()], "added": int(p.shape[0]),
                                     "velocity": list(map(float, velocity))}])


def nearest_index(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a``, the index of the nearest point of ``b`` (a KD-tree)."""
    from scipy.spatial import cKDTree

    return cKDTree(b).query(a, k=1)[1].astype(np.int64)


__all__ = ["remove_fraction", "remove_box", "remove_sphere", "translate", "add_box", "nearest_index"]
