"""Exports of a reconstruction for other tools (paper Sec. 4.3; ``gf-cli export``).

- ``ply``: the Gaussians at one time as a 3DGS PLY (binary little-endian; the properties common
  3DGS viewers read: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3, with the
  activations 3DGS expects: logit opacity, log scales, quaternion w x y z, SH coefficients with
  f_rest channel-major). Grayscale reconstructions are written with their channel in all three.
  The SH are written at degree 3 by default (``sh_degree``), higher coefficients zero: the
  reference 3DGS reader (``GaussianModel.load_ply``) and most viewers expect exactly 45 f_rest
  properties and refuse or misread others; a lower degree drops the coefficients above it.
- ``gltf``: the Gaussians at one time as binary glTF 2.0 (``.glb``) with the Khronos
  ``KHR_gaussian_splatting`` extension: a POINTS primitive with POSITION, ``:SCALE`` (log),
  ``:ROTATION`` (unit quaternion x y z w), ``:OPACITY`` (in [0, 1]), ``:SH_DEGREE_l_COEF_n`` (RGB,
  every coefficient of the model's degree), COLOR_0 (base colour and opacity, for viewers that
  draw plain points); kernel ellipse, colour space srgb_rec709_display. The node turns the
  toolkit's z-up world into glTF's y-up.
- ``particles``: per frame a PLY of points: x y z vx vy vz radius opacity (velocities from the
  decoder's time derivative, m/s).
- ``vtk``: per frame a legacy VTK file (an unstructured grid of vertex cells, binary) of the same points, with ``velocity``
  as a 3-vector and ``radius``, ``opacity`` as scalars: what meshio-based loaders (Blender's
  sequence loader, ParaView) read as a ``velocity`` vector attribute (motion blur), which no PLY
  reader gives (PLY properties are scalars).
- ``vdb``: per frame an OpenVDB float grid ``density``, class fog volume (``formats/caches.py``).
- ``usd``: one USD file of points with time samples: positions, widths, velocities, and the
  base colour and opacity of every point as ``displayColor`` / ``displayOpacity`` (``formats/caches.py``).
- ``usd-splats``: one USD file of OpenUSD's 3D Gaussian splats (``ParticleField3DGaussianSplat``,
  OpenUSD 26.03 and later) with time samples: positions, orientations, scales, opacities and the
  SH coefficients of every Gaussian (``formats/caches.py``).

Times: by default the reconstruction's training frames (``frame_times_s`` in recon.h5), else a
grid at ``fps`` over the clip; ``--fps`` resamples the clip (the decoder is continuous).
Numpy only (the decoder is ``formats/decoder_np.py``, the writers ``formats/``); pxr/openvdb for usd/vdb.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..formats.decoder_np import ParticleAnimation
from ..formats.gltf import write_gaussians_glb
from ..formats.ply import gaussians_to_ply_columns, write_ply
from ..formats.vtk import write_vtk_points

FORMATS = ("ply", "gltf", "particles", "vtk", "vdb", "usd", "usd-splats")


# ---- times ----------------------------------------------------------------------------------------
def export_times(recon, *, frames: slice | None = None, fps: float | None = None) -> list[float]:
    """Seconds to export: the training frames (or a grid at ``fps``), sliced by ``frames``."""
    t0, t1 = float(recon.time_min), float(recon.time_max)
    if fps is not None:
        if not fps > 0:
            raise InputError("--fps", f"must be > 0, got {fps}")
        times = list(t0 + np.arange(int(np.floor((t1 - t0) * fps + 1e-6)) + 1) / fps)
    else:
        times = [float(t) for t in (recon.config or {}).get("frame_times_s") or []]
        if not times:
            f = (recon.config or {}).get("fps") or 30.0
            times = list(t0 + np.arange(int(np.floor((t1 - t0) * f + 1e-6)) + 1) / f)
    if recon.decoder is None:
        times = times[:1]  # a static reconstruction has one state
    sel = times[frames] if frames is not None else times
    if not sel:
        raise InputError("--frames", f"selects none of the {len(times)} frames")
    return sel


def sample_rate(times, fps: float | None = None, *, where="reconstruction") -> float:
    """Samples per second of evenly spaced ``times`` (the k-th time is time code k of a USD
    cache, so this is its timeCodesPerSecond and playback runs in real time); one time: ``fps``,
    else 30. Unevenly spaced times have no one rate: a clear error asking for --fps."""
    t = np.asarray(times, np.float64)
    if len(t) < 2:
        return float(fps or 30.0)
    dt = np.diff(t)
    if not dt.min() > 0 or dt.max() > 1.01 * dt.min():
        raise InputError(where, f"its {len(t)} frame times are not evenly spaced ({dt.min():.4g} to {dt.max():.4g} s "
                                "apart), so they have no one frame rate; give --fps to resample the clip evenly")
    return round(float(1.0 / dt.mean()), 6)


# ---- the exports ----------------------------------------------------------------------------------
def export_ply(anim: ParticleAnimation, t: float, path, *, sh_degree: int | None = 3) -> Path:
    g = anim.at(t, warn=True)
    return write_ply(path, gaussians_to_ply_columns(g["positions"], g["log_scales"], g["quats"],
                                                    g["logit_opacity"], g["sh"], sh_degree=sh_degree))


def export_gltf(anim: ParticleAnimation, t: float, path) -> Path:
    g = anim.at(t, warn=True)
    return write_gaussians_glb(path, g["positions"], g["log_scales"], g["quats"], g["logit_opacity"], g["sh"],
                               generator=f"gaussfluids (t = {float(t):.6g} s)")


def particle_radii(log_scales, radius_scale: float = 1.0):
    """A point radius per particle: ``radius_scale`` x the geometric mean of its Gaussian scales."""
    return radius_scale * np.exp(np.asarray(log_scales, np.float64).mean(1))


def export_particles(anim: ParticleAnimation, times, out_dir, radius_scale: float = 1.0) -> list[Path]:
    out = []
    for k, t in enumerate(times):
        g = anim.at(t, velocity=True, warn=True)
        p, v = g["positions"], g["velocities"]
        out.append(write_ply(Path(out_dir) / f"particles_{k:05d}.ply", {
            "x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
            "radius": particle_radii(g["log_scales"], radius_scale), "opacity": g["opacities"]}))
    return out


def export_vtk(anim: ParticleAnimation, times, out_dir, radius_scale: float = 1.0) -> list[Path]:
    out = []
    for k, t in enumerate(times):
        g = anim.at(t, velocity=True, warn=True)
        out.append(write_vtk_points(Path(out_dir) / f"particles_{k:05d}.vtk", g["positions"],
                                    {"velocity": g["velocities"]},
                                    {"radius": particle_radii(g["log_scales"], radius_scale), "opacity": g["opacities"]},
                                    title=f"gaussfluids particles t={float(t):.6g} s"))
    return out


def export_vdb(anim: ParticleAnimation, times, out_dir, *, voxel: float | None = None,
               radius_scale: float = 1.0) -> list[Path]:
    from ..formats.caches import density_grid, write_vdb_density

    out = []
    for k, t in enumerate(times):
        g = anim.at(t, warn=True)
        sig = particle_radii(g["log_scales"], radius_scale)
        vx = voxel or 0.5 * float(np.median(sig))
        dense, lo = density_grid(g["positions"], sig, g["opacities"], vx)
        out.append(Path(write_vdb_density(Path(out_dir) / f"density_{k:05d}.vdb", dense, lo, vx)))
    return out


def export_usd(anim: ParticleAnimation, times, path, *, fps: float, radius_scale: float = 1.0) -> Path:
    """Time code k = the k-th exported time; ``fps`` time codes per second."""
    from ..formats.caches import write_usd_points

    def samples():
        for k, t in enumerate(times):
            g = anim.at(t, velocity=True, warn=True)
            yield k, g["positions"], particle_radii(g["log_scales"], radius_scale), g["velocities"], \
                g["colors"], g["opacities"]

    return Path(write_usd_points(path, samples(), fps=fps, start=0, end=len(times) - 1,
                                 metadata={"times_s": [float(t) for t in times]}))


def export_usd_splats(anim: ParticleAnimation, times, path, *, fps: float) -> Path:
    """The Gaussians as OpenUSD 3D Gaussian splats; time code k = the k-th exported time."""
    from ..formats.caches import write_usd_gaussians

    def samples():
        for k, t in enumerate(times):
            g = anim.at(t, warn=True)
            yield k, g["positions"], g["log_scales"], g["quats"], g["logit_opacity"], g["sh"], g["colors"]

    return Path(write_usd_gaussians(path, samples(), fps=fps, start=0, end=len(times) - 1,
                                    metadata={"times_s": [float(t) for t in times]}))


__all__ = ["FORMATS", "export_times", "sample_rate", "export_ply", "export_gltf", "export_particles", "export_vtk",
           "export_vdb", "export_usd", "export_usd_splats", "particle_radii"]
