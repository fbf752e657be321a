"""The native C++ CPU backend: built on first use with ``torch.utils.cpp_extension`` and cached.

If it cannot be built (no compiler, or ``GF_NO_NATIVE=1``), ``available()`` is False, one
warning line says why, and ``render`` falls back to the pure-torch reference backend.
"""

from __future__ import annotations

import hashlib
import os
import platform
import warnings
from pathlib import Path

import torch

CSRC = Path(__file__).parent / "csrc"
_ext = None
_error: str | None = None


def _build_dir() -> Path:
    # -march=native code is tied to the CPU: key the cache on it and on torch's version
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = "".join(line for line in f if line.startswith(("model name", "flags")))[:4000]
    except OSError:
        cpu = platform.processor()
    tag = hashlib.sha1(f"{cpu}|{torch.__version__}|{platform.python_version()}".encode()).hexdigest()[:12]
    root = Path(os.environ.get("GF_EXT_DIR", Path.home() / ".cache" / "gaussfluids" / "torch_extensions"))
    d = root / f"cpu-{tag}"
    d.mkdir(parents=True, exist_ok=True)
    return d


def load():
    """The compiled extension module, or None (with one warning) if it cannot be built."""
    global _ext, _error
    if _ext is not None or _error is not None:
        return _ext
    if os.environ.get("GF_NO_NATIVE", "") not in ("", "0"):
        _error = "disabled by GF_NO_NATIVE"
        return None
    try:
        from torch.utils.cpp_extension import load as load_ext

        flags = ["-O3", "-fopenmp", "-march=native"]
        _ext = load_ext(name="gf_render_cpu", sources=[str(CSRC / "render_cpu.cpp")],
                        extra_include_paths=[str(CSRC)], extra_cflags=flags,
                        extra_ldflags=["-fopenmp"], build_directory=str(_build_dir()),
                        verbose=os.environ.get("GF_NATIVE_VERBOSE", "") not in ("", "0"))
    except Exception as e:  # no compiler, missing headers, ...: fall back, say so once
        lines = str(e).strip().splitlines()
        first_error = next((ln.strip() for ln in lines if "error" in ln.lower()), lines[-1] if lines else "")
        _error = f"{type(e).__name__}: {first_error}"[:300]
        warnings.warn(f"gaussfluids: native CPU renderer unavailable ({_error}); using the pure-torch "
                      "reference backend, which is much slower", RuntimeWarning, stacklevel=3)
        _ext = None
    return _ext


def available() -> bool:
    return load() is not None


def unavailable_reason() -> str | None:
    load()
    return _error


def _zeros_if_none(g, like):
    return torch.zeros_like(like) if g is None else g


class ProjectFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, scales, quats, opacities, sh, viewmat, intr, width, height, near,
                min_alpha, degree):
        ext = load()
        m2d, con, dep, col, radii = ext.project_forward(means, scales, quats, opacities, sh, viewmat,
                                                        intr, width, height, near, min_alpha, degree)
        ctx.save_for_backward(means, scales, quats, sh, viewmat, intr, radii)
        ctx.cfg = (width, height, near, degree)
        ctx.mark_non_differentiable(radii)
        return m2d, con, dep, col, radii

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, g_col, _g_radii):
        means, scales, quats, sh, viewmat, intr, radii = ctx.saved_tensors
        width, height, near, degree = ctx.cfg
        n, c = means.shape[0], sh.shape[2]
        g_m2d = _zeros_if_none(g_m2d, means[:, :2])
        g_con = _zeros_if_none(g_con, means)
        g_dep = _zeros_if_none(g_dep, means[:, 0])
        g_col = g_col if g_col is not None else means.new_zeros(n, c)
        gm, gs, gq, gsh = load().project_backward(means, scales, quats, sh, viewmat, intr, width, height,
                                                  near, degree, radii, g_m2d, g_con, g_dep, g_col)
        return gm, gs, gq, None, gsh, None, None, None, None, None, None, None


class RasterizeFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, background, radii, depths, width, height,
                tile, min_alpha):
        out, T, nc, offsets, ids = load().rasterize_forward(means2d, conics, opacities, features,
                                                            background, radii, depths, width, height,
                                                            tile, min_alpha)
        ctx.save_for_backward(means2d, conics, opacities, radii, features, background, offsets, ids, T, nc)
        ctx.cfg = (width, height, tile, min_alpha)
        return out, T

    @staticmethod
    def backward(ctx, g_out, g_T):
        means2d, conics, opacities, radii, features, background, offsets, ids, T, nc = ctx.saved_tensors
        width, height, tile, min_alpha = ctx.cfg
        g_out = _zeros_if_none(g_out, means2d.new_zeros(height, width, features.shape[1]))
        g_T = _zeros_if_none(g_T, T)
        gm, gc, go, gf = load().rasterize_backward(means2d, conics, opacities, radii, features, background,
                                                   offsets, ids, T, nc, g_out, g_T, width, height,
                                                   tile, min_alpha)
        return gm, gc, go, gf, None, None, None, None, None, None, None
