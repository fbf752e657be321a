"""Bakes: the decoded animation as a USD points cache and, for smoke, OpenVDB density grids.

The file writing is the toolkit's (``gf_core/formats/caches.py``, shared with ``gf-cli export``); this
module samples the reconstruction at scene frames.
"""

import os
import sys

import bpy
import numpy as np

from .gf_core.formats import caches


def _blender_site_packages():
    py = f"python{sys.version_info.major}.{sys.version_info.minor}"
    return [os.path.join(base, "python", "lib", py, "site-packages")
            for base in (bpy.utils.resource_path("LOCAL"), bpy.utils.resource_path("SYSTEM"))]


def bundled_module(name: str):
    """pxr / openvdb as this Blender bundles them (also under the bpy module)."""
    return caches.bundled_module(name, _blender_site_packages())


def frame_samples(frame_start: int, frame_end: int, substeps: int) -> list:
    """Scene frames to sample: every frame and ``substeps - 1`` sub-frames between frames."""
    if frame_end < frame_start:
        raise ValueError(f"frame range {frame_start}..{frame_end} is empty")
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    out = []
    for f in range(frame_start, frame_end + 1):
        out += [f + k / substeps for k in range(substeps if f < frame_end else 1)]
    return out


def bake_usd(anim, path: str, frames: list, times_s: list, *, fps: float, radius_scale: float,
             velocity: bool = True) -> str:
    """Time codes = scene frames (``fps`` per second); positions, radii, velocities, base colours
    and opacities of the reconstruction at ``times_s``."""
    if len(frames) != len(times_s) or not frames:
        raise ValueError("need one time per frame, at least one frame")

    def samples():
        for f, t in zip(frames, times_s):
            res = anim.at(t, velocity=velocity, warn=False)
            yield f, res["positions"], radius_scale * np.exp(res["log_scales"].mean(1)), res.get("velocities"), \
                res["colors"], res["opacities"]

    return caches.write_usd_points(path, samples(), fps=fps, start=frames[0], end=frames[-1],
                                   metadata={"source": os.path.basename(anim.source or "")},
                                   extra_paths=_blender_site_packages())


def read_usd_points(path: str, frame: float) -> np.ndarray:
    return caches.read_usd_points(path, frame, _blender_site_packages())


def bake_vdb(anim, directory: str, frames: list, times_s: list, *, voxel: float, radius_scale: float) -> list:
    """``density_FFFFF.vdb`` per whole frame: the particles' Gaussians (std = radius_scale x
    geometric-mean scale, amplitude = opacity) on a grid of ``voxel``."""
    written = []
    for f, t in zip(frames, times_s):
        res = anim.at(t, warn=False)
        dense, lo = caches.density_grid(res["positions"], radius_scale * np.exp(res["log_scales"].mean(1)),
                                        res["opacities"], voxel)
        written.append(caches.write_vdb_density(os.path.join(directory, f"density_{int(f):05d}.vdb"), dense, lo,
                                                voxel, extra_paths=_blender_site_packages()))
    return written
