"""TOML files the toolkit reads (presets and configs, scene suites, batch suites), with errors
that name the file."""

from __future__ import annotations

import tomllib
from pathlib import Path

from ..errors import InputError


def read_toml(path, what: str = "file") -> dict:
    """The parsed file; a missing file or bad TOML is an InputError naming it (``what``: e.g.
    "config file")."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, f"{what} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(path, f"not valid TOML ({e})") from None
