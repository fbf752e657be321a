"""Refusing before work what this machine cannot hold: memory estimates against the memory free."""

from __future__ import annotations

import os

from .errors import InputError


# a simulated particle at least: state, neighbour lists and per-step buffers of the SPH solvers (bytes)
PARTICLE_BYTES = 512


def available_bytes() -> int:
    """Memory a new allocation can get: MemAvailable (free + reclaimable cache) where the kernel
    reports it, else the free physical pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 62  # unknown: nothing is refused


def require_memory(where: str, what: str, need: float, *, fraction: float = 0.8) -> None:
    """Refuse (one line naming ``where``) when ``what`` needs more than ``fraction`` of the free memory."""
    avail = available_bytes()
    if need > fraction * avail:
        raise InputError(where, f"{what} need about {need / 2**30:.3g} GiB; this machine has "
                                f"{avail / 2**30:.3g} GiB free")


def check_seed(where: str, seed) -> int:
    """A seed every generator accepts (numpy, torch, Blender's 32-bit one is mapped separately)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise InputError(where, f"a seed must be an integer in [0, 2^63), got {seed!r}")
    return seed
