"""Checks of options that several commands share: the device, a frame slice, output paths.
Each refuses a bad value in one line naming the option, before any work."""

from __future__ import annotations

import os
from pathlib import Path

from gf_core.errors import InputError


def check_device(device: str) -> str:
    import torch

    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError("--device", f"unknown device {device!r}; use cpu or cuda")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("--device", "cuda was asked for but torch sees no CUDA GPU on this machine; use --device cpu")
    return device


def parse_frames(spec: str) -> slice:
    """START:END:STEP (python slice syntax, integers: "5" is the first five) -> slice; errors name --frames."""
    parts = spec.split(":")
    if len(parts) not in (1, 2, 3):
        raise InputError("--frames", f"must be START:END:STEP, got {spec!r}")
    vals = []
    for p in parts:
        p = p.strip()
        if p == "":
            vals.append(None)
            continue
        try:
            vals.append(int(p))
        except ValueError:
            raise InputError("--frames", f"{p!r} is not an integer (in {spec!r}; expected START:END:STEP)") from None
    if len(vals) == 3 and vals[2] is not None and vals[2] <= 0:
        raise InputError("--frames", f"STEP must be a positive integer, got {vals[2]}")
    return slice(*vals)


def check_out_file(path: Path, flag: str = "--out") -> None:
    """An output file we will be able to write, checked before any work: not a folder, a parent
    that is (or can be made) a writable folder."""
    path = Path(path)
    if path.exists() and path.is_dir():
        raise InputError(path, f"{flag} names a folder; give a file name (e.g. {path / 'sim.h5'})")
    _writable_from(path, path.parent, flag)


def check_out_dir(path: Path, flag: str = "--out") -> None:
    """An output folder we will be able to write, checked before any work: not an existing file,
    and it (or the nearest folder above it that exists) writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, f"{flag} must be a folder, and this is a file")
    _writable_from(path, path, flag)


def _writable_from(path: Path, start: Path, flag: str) -> None:
    """The nearest of ``start`` and its parents that exists is a folder we may write in."""
    for up in [start, *start.parents]:
        if up.exists():
            if not up.is_dir():
                raise InputError(path, f"{flag}: {up} is a file, so it cannot hold {path.name}")
            if not os.access(up, os.W_OK | os.X_OK):
                raise InputError(path, f"{flag}: {up} is not writable")
            return
