"""Particle caches for other tools: USD points with time samples, OpenVDB density grids.

Numpy only, plus the ``pxr`` and ``openvdb`` modules that Blender bundles: inside a Blender
binary they import directly; with Blender as a Python module (the bpy wheel) they sit in its own
site-packages, which ``bundled_module`` finds without importing bpy. Used by the Blender
extension's bakes and by ``gf-cli export`` (one implementation; no torch, so the extension
carries this file). Files are written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import os
import sys
from pathlib import Path

import numpy as np


def _bpy_site_packages() -> list:
    """Blender's own site-packages folders, found from the bpy wheel's files (bpy not imported)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return []
    py = f"python{sys.version_info.major}.{sys.version_info.minor}"
    out = []
    for loc in spec.submodule_search_locations:
        for ver in sorted(Path(loc).glob("[0-9]*.[0-9]*")):
            for sp in (ver / "python" / "lib" / py / "site-packages", ver / "python" / "lib" / "site-packages"):
                if sp.is_dir():
                    out.append(str(sp))
    return out


def bundled_module(name: str, extra_paths=()):
    """Import ``pxr`` or ``openvdb``: directly, else from Blender's bundled site-packages."""
    try:
        return importlib.import_module(name)
    except ImportError:
        pass
    for sp in list(extra_paths) + _bpy_site_packages():
        if os.path.isdir(sp) and sp not in sys.path:
            sys.path.append(sp)
    try:
        return importlib.import_module(name)
    except ImportError as e:
        raise ImportError(f"the '{name}' module is not importable: it comes with Blender (the bpy module, "
                          f"`pip install bpy==5.0.1`, or a Blender binary){' or usd-core' if name == 'pxr' else ''} "
                          f"({e})") from None


def _tmp_for(path) -> str:
    head, tail = os.path.split(os.path.abspath(path))
    stem, ext = os.path.splitext(tail)
    return os.path.join(head, f".{stem}.partial{ext}")


def write_usd_points(path, samples, *, fps: float, start: float, end: float, metadata: dict | None = None,
                     extra_paths=()) -> str:
    """UsdGeom.Points at /gaussfluids/particles (default prim /gaussfluids, kind component),
    time-sampled.

    ``samples``: iterable of (time code, positions (N, 3), radii (N,), velocities (N, 3) or None,
    and optionally colours (N, 3) in [0, 1] and opacities (N,)); ``fps`` time codes per second;
    ``start``/``end`` the stage's time range. Widths are 2 x radii; colours and opacities become
    the ``displayColor`` / ``displayOpacity`` primvars per point (what Houdini, Omniverse and
    usdview show); up axis z, 1 metre per unit (Blender's conventions)."""
    bundled_module("pxr", extra_paths)
    from pxr import Usd, UsdGeom, Vt

    path = str(path)
    stage, tmp = _new_stage(path, fps, start, end)
    pts = UsdGeom.Points.Define(stage, "/gaussfluids/particles")
    pa, wa, ext = pts.CreatePointsAttr(), pts.CreateWidthsAttr(), pts.CreateExtentAttr()
    va = ca = oa = None
    pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    n_samples = 0
    for code, p, r, v, *look in samples:
        p = np.ascontiguousarray(p, np.float32)
        r = np.ascontiguousarray(r, np.float32)
        tc = Usd.TimeCode(float(code))
        pa.Set(Vt.Vec3fArray.FromNumpy(p), tc)
        wa.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(2 * r)), tc)
        if v is not None:
            va = va or pts.CreateVelocitiesAttr()
            va.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v, np.float32)), tc)
        if look:
            col, opa = look
            if ca is None:
                ca = pts.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
                oa = pts.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex)
            ca.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(np.clip(col, 0, 1), np.float32)), tc)
            oa.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(np.clip(opa, 0, 1), np.float32)), tc)
        if len(p):
            ext.Set(Vt.Vec3fArray.FromNumpy(np.stack([(p - r[:, None]).min(0), (p + r[:, None]).max(0)])), tc)
        n_samples += 1
    if n_samples == 0:
        raise ValueError("no time samples to write")
    _finish_stage(stage, tmp, path, metadata)
    return path


def _new_stage(path: str, fps: float, start: float, end: float):
    """A new stage at a temporary name beside ``path``: z up, 1 metre per unit, ``fps`` time codes
    per second over [start, end], default prim /gaussfluids (an Xform of kind component)."""
    from pxr import Kind, Usd, UsdGeom

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = _tmp_for(path)
    if os.path.exists(tmp):
        os.remove(tmp)
    stage = Usd.Stage.CreateNew(tmp)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(float(start))
    stage.SetEndTimeCode(float(end))
    root = UsdGeom.Xform.Define(stage, "/gaussfluids")
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    return stage, tmp


def _finish_stage(stage, tmp: str, path: str, metadata: dict | None) -> None:
    """The layer's custom data (generator, ``metadata``), saved, then moved to ``path``."""
    from pxr import Vt

    meta = {"generator": "GaussFluids"}
    for k, v in (metadata or {}).items():  # USD dictionaries hold typed arrays, not Python lists
        meta[k] = Vt.DoubleArray([float(x) for x in v]) if isinstance(v, (list, tuple)) else v
    stage.GetRootLayer().customLayerData = meta
    stage.GetRootLayer().Save()
    del stage
    os.replace(tmp, path)


SPLAT_TYPE = "ParticleField3DGaussianSplat"


def write_usd_gaussians(path, samples, *, fps: float, start: float, end: float, metadata: dict | None = None,
                        extra_paths=()) -> str:
    """OpenUSD's 3D Gaussian splats (``UsdVolParticleField3DGaussianSplat``, OpenUSD 26.03 and
    later) at /gaussfluids/gaussians, time-sampled.

    ``samples``: iterable of (time code, positions (N, 3), log scales (N, 3), quaternions w x y z
    (N, 4, any norm), logit opacities (N,), SH coefficients (N, K, 1 or 3) in the 3DGS basis and
    order, base colours (N, 3)). Written as the schema defines them: linear ``scales`` (the
    Gaussian's standard deviations), unit ``orientations``, ``opacities`` in [0, 1],
    ``radiance:sphericalHarmonicsCoefficients`` K per particle, contiguous (grayscale repeated in R,
    G and B), ``radiance:sphericalHarmonicsDegree``; ``displayColor`` / ``displayOpacity`` for
    viewers that draw points. The prim's type and attributes are authored by name, so any pxr
    writes them (Blender's included); readers of 26.03 and later see the typed schema."""
    from .decoder_np import sigmoid, unit_quaternions

    bundled_module("pxr", extra_paths)
    from pxr import Gf, Sdf, Usd, Vt

    path = str(path)
    stage, tmp = _new_stage(path, fps, start, end)
    prim = stage.DefinePrim("/gaussfluids/gaussians", SPLAT_TYPE)
    T = Sdf.ValueTypeNames
    attrs = {name: prim.CreateAttribute(name, kind) for name, kind in (
        ("positions", T.Point3fArray), ("orientations", T.QuatfArray), ("scales", T.Float3Array),
        ("opacities", T.FloatArray), ("radiance:sphericalHarmonicsCoefficients", T.Float3Array),
        ("primvars:displayColor", T.Color3fArray), ("primvars:displayOpacity", T.FloatArray),
        ("extent", T.Float3Array))}
    for name in ("primvars:displayColor", "primvars:displayOpacity"):
        attrs[name].SetMetadata("interpolation", "vertex")
    degree_attr = prim.CreateAttribute("radiance:sphericalHarmonicsDegree", T.Int, variability=Sdf.VariabilityUniform)
    degree = None
    n_samples = 0
    for code, p, log_s, q, logit_o, sh, color in samples:
        p = np.ascontiguousarray(p, np.float32)
        sh = np.asarray(sh, np.float32)
        if sh.shape[2] == 1:
            sh = np.repeat(sh, 3, axis=2)
        k = sh.shape[1]
        d = int(round(math.sqrt(k))) - 1
        if (d + 1) ** 2 != k or (degree is not None and d != degree):
            raise ValueError(f"{k} SH coefficients per particle is not (degree + 1)^2 of one degree")
        degree = d
        q = unit_quaternions(q)
        scales = np.exp(np.asarray(log_s, np.float64))
        opacity = sigmoid(np.asarray(logit_o, np.float64))
        tc = Usd.TimeCode(float(code))
        attrs["positions"].Set(Vt.Vec3fArray.FromNumpy(p), tc)
        # GfQuatf's memory (and so FromNumpy's columns) is the imaginary part, then the real one
        attrs["orientations"].Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(q[:, [1, 2, 3, 0]], np.float32)), tc)
        attrs["scales"].Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(scales, np.float32)), tc)
        attrs["opacities"].Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(opacity, np.float32)), tc)
        attrs["radiance:sphericalHarmonicsCoefficients"].Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(sh.reshape(-1, 3))), tc)
        attrs["primvars:displayColor"].Set(
            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(np.clip(color, 0, 1), np.float32)), tc)
        attrs["primvars:displayOpacity"].Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(opacity, np.float32)), tc)
        if len(p):  # three standard deviations hold the drawn part of each Gaussian
            reach = 3.0 * scales.max(1, keepdims=True)
            attrs["extent"].Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, (p - reach).min(0))),
                                               Gf.Vec3f(*map(float, (p + reach).max(0)))]), tc)
        n_samples += 1
    if n_samples == 0:
        raise ValueError("no time samples to write")
    degree_attr.Set(int(degree))
    _finish_stage(stage, tmp, path, metadata)
    return path


def read_usd_points(path, code: float, extra_paths=()) -> np.ndarray:
    """Positions (N, 3) of a cache written by ``write_usd_points`` at time code ``code``."""
    bundled_module("pxr", extra_paths)
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise ValueError(f"{path}: not a USD file")
    prim = stage.GetPrimAtPath("/gaussfluids/particles")
    if not prim.IsValid():
        raise ValueError(f"{path}: has no /gaussfluids/particles points")
    return np.asarray(UsdGeom.Points(prim).GetPointsAttr().Get(Usd.TimeCode(float(code))), np.float32)


def density_grid(positions, sigmas, weights, voxel: float, *, cutoff: float = 3.0, max_reach: int = 6):
    """Sum of isotropic Gaussians (amplitude ``weights``, std ``sigmas``) on a voxel grid.

    Returns (dense (X, Y, Z) float32, world position of voxel (0, 0, 0)'s corner). Each particle
    touches the voxels whose centres lie within ``cutoff`` std (at most ``max_reach`` voxels each
    way); vectorised with bincount over blocks of particles."""
    positions = np.asarray(positions, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or not len(positions):
        raise ValueError(f"positions must be (N >= 1, 3), got {positions.shape}")
    if not voxel > 0:
        raise ValueError(f"voxel size must be > 0, got {voxel}")
    sigmas = np.maximum(np.broadcast_to(np.asarray(sigmas, np.float64), (len(positions),)), 1e-6 * voxel)
    weights = np.broadcast_to(np.asarray(weights, np.float64), (len(positions),))
    pad = cutoff * float(sigmas.max()) + voxel
    lo = positions.min(0) - pad
    dims = np.maximum(np.ceil((positions.max(0) + pad - lo) / voxel).astype(int) + 1, 1)
    if float(np.prod(dims.astype(np.float64))) > 512 ** 3:
        from ..errors import InputError

        raise InputError("--voxel", f"a voxel of {voxel:.3g} m makes a {' x '.join(map(str, dims.tolist()))} grid "
                                    f"around the particles, more than 512^3 voxels; choose a larger voxel size")
    reach = int(min(max_reach, math.ceil(cutoff * float(sigmas.max()) / voxel)))
    off = np.arange(-reach, reach + 1)
    stencil = np.stack(np.meshgrid(off, off, off, indexing="ij"), -1).reshape(-1, 3)
    centre = np.floor((positions - lo) / voxel).astype(int)
    dense = np.zeros(int(np.prod(dims)), np.float64)
    for s in range(0, len(positions), 4096):  # blocks bound the memory of the stencil
        c = centre[s:s + 4096, None, :] + stencil[None]
        d2 = (((c + 0.5) * voxel + lo - positions[s:s + 4096, None, :]) ** 2).sum(-1)
        sig = sigmas[s:s + 4096, None]
        val = weights[s:s + 4096, None] * np.exp(-0.5 * d2 / sig ** 2)
        ok = np.all((c >= 0) & (c < dims), -1) & (d2 <= (cutoff * sig) ** 2)
        flat = np.ravel_multi_index(tuple(c[ok].T), dims)
        dense += np.bincount(flat, weights=val[ok], minlength=dense.size)
    return dense.reshape(dims).astype(np.float32), lo


def write_vdb_density(path, dense: np.ndarray, lo, voxel: float, *, name: str = "density", extra_paths=()) -> str:
    """One float grid ``name`` from a dense array: voxel (i, j, k) centred at lo + (ijk + 0.5) voxel."""
    vdb = bundled_module("openvdb", extra_paths)
    grid = vdb.FloatGrid()
    grid.copyFromArray(np.ascontiguousarray(dense, np.float32), ijk=(0, 0, 0), tolerance=0.0)
    grid.name = name
    grid.gridClass = vdb.GridClass.FOG_VOLUME  # a density in [0, ...), zero outside: what renderers shade as a volume
    m = np.eye(4)
    m[0, 0] = m[1, 1] = m[2, 2] = voxel
    m[3, :3] = np.asarray(lo, np.float64) + 0.5 * voxel  # row-vector matrices: translation in the last row
    grid.transform = vdb.createLinearTransform(m.tolist())
    path = str(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = _tmp_for(path)
    vdb.write(tmp, grids=[grid])
    os.replace(tmp, path)
    return path


def read_vdb_density(path, shape, *, name: str = "density", extra_paths=()) -> np.ndarray:
    """The grid's values on voxels (0, 0, 0) .. shape - 1, as a dense array (for checks)."""
    vdb = bundled_module("openvdb", extra_paths)
    grid = vdb.read(str(path), name)
    out = np.zeros(tuple(shape), np.float32)
    grid.copyToArray(out, ijk=(0, 0, 0))
    return out


__all__ = ["bundled_module", "write_usd_points", "read_usd_points", "write_usd_gaussians", "SPLAT_TYPE", "density_grid", "write_vdb_density",
           "read_vdb_density"]
