"""JSON fields every dataset layout reads the same way (one line naming the file and the key
for a wrong type, shape or value): the file itself, paths, matrices, numbers, view ids, intrinsics
and the background colour. The layouts (``nerf``, ``video``, ``colmap``) import these; none
imports another layout."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..errors import InputError, short_repr


def read_json(path: Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file does not exist")
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as e:
        raise InputError(path, f"malformed JSON: {e}") from None
    except UnicodeDecodeError as e:
        raise InputError(path, f"not UTF-8 text (JSON must be UTF-8): byte {e.start} cannot be decoded") from None
    except RecursionError:
        raise InputError(path, "JSON nested too deeply to be a dataset description") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object at the top level")
    return data


def path_value(d: dict, key: str, json_path: Path, where: str) -> str | None:
    """``d[key]`` as a file path (a non-empty string), None when absent or null."""
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, str) or not v:
        raise InputError(json_path, f"{where}: {key!r} must be a file path (a non-empty string), got {short_repr(v)}")
    return v


def matrix_value(v, json_path: Path, where: str, key: str, shapes=((4, 4), (3, 4))) -> np.ndarray:
    """A JSON matrix as float64 of one of ``shapes``, finite, else one line naming the key."""
    want = " or ".join(f"{r}x{c}" for r, c in shapes)
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        a = None
    if a is None or a.shape not in shapes:
        raise InputError(json_path, f"{where}: {key!r} must be a {want} matrix of numbers, got {short_repr(v)}")
    if not np.all(np.isfinite(a)):
        raise InputError(json_path, f"{where}: {key!r} contains NaN or infinite values")
    return a


def number(d: dict, key: str, json_path: Path, where: str):
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise InputError(json_path, f"{where}: {key!r} must be a finite number, got {v!r}")
    return float(v)


VIEW_KEYS = ("view_id", "view", "camera_id")


def view_id(entry: dict, json_path: Path, where: str, default: int | None = None) -> int | None:
    """A frame's or camera's view id from ``view_id``, ``view`` or ``camera_id`` (an integer)."""
    key = next((k for k in VIEW_KEYS if k in entry), None)
    if key is None:
        return default
    raw = entry[key]
    if isinstance(raw, bool) or not isinstance(raw, (int, float, str)) or not str(raw).strip().lstrip("-").isdigit():
        raise InputError(json_path, f"{where}: {key!r} must be an integer, got {raw!r}")
    return int(str(raw).strip())


def intrinsics(d: dict, json_path: Path, where: str):
    """(fl_x, fl_y, camera_angle_x, camera_angle_y, cx, cy) from a transforms frame or a camera
    entry, each None when absent, validated the same way for every layout."""
    fx, fy = number(d, "fl_x", json_path, where), number(d, "fl_y", json_path, where)
    angle, angle_y = number(d, "camera_angle_x", json_path, where), number(d, "camera_angle_y", json_path, where)
    if fx is None and fy is None and angle is None and angle_y is None:
        raise InputError(json_path, f"{where}: no focal length (need 'camera_angle_x' or 'fl_x')")
    if (fx is not None and fx <= 0) or (fy is not None and fy <= 0):
        raise InputError(json_path, f"{where}: focal length must be positive (fl_x={fx}, fl_y={fy})")
    for name, a in (("camera_angle_x", angle), ("camera_angle_y", angle_y)):
        if a is not None and not 0 < a < math.pi:
            raise InputError(json_path, f"{where}: {name} must be a field of view in (0, pi) radians, got {a}")
    return fx, fy, angle, angle_y, number(d, "cx", json_path, where), number(d, "cy", json_path, where)


def background(meta: dict, channels: int, json_path: Path | str = "dataset") -> tuple:
    bg = meta.get("background", [0.0, 0.0, 0.0])
    vals = [bg] if isinstance(bg, (int, float)) and not isinstance(bg, bool) else bg
    if not isinstance(vals, list) or len(vals) not in (1, 3) or \
            any(isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 <= x <= 1 for x in vals):
        raise InputError(json_path, f"'background' must be a colour: a number or 3 numbers in [0, 1], got {short_repr(bg)}")
    vals = [float(x) for x in vals] * (3 if len(vals) == 1 else 1)
    return tuple(vals[:channels]) if channels == 1 else tuple(vals[:3])
