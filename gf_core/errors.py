"""Errors that name the file (or object) and the problem."""

from __future__ import annotations

import os


def short_repr(v, n: int = 60) -> str:
    """A bad value for an error message: its repr (arrays as lists, bytes decoded), cut to ``n``."""
    if isinstance(v, bytes):
        v = v.decode(errors="replace")
    if hasattr(v, "tolist"):
        v = v.tolist()
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."


class GFError(Exception):
    """Base class of every error the toolkit raises on purpose."""


class ReconstructionError(GFError):
    """A reconstruction cannot continue (non-finite steps, a resume that does not match, ...)."""


class InputError(GFError, ValueError):
    """Bad input: ``<where>: <problem>``. ``where`` is usually a file path."""

    def __init__(self, where: "str | os.PathLike[str]", problem: str):
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")


class FormatError(InputError):
    """A file is not of the expected format or version, or fails validation."""
