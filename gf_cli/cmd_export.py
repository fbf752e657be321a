"""``gf-cli export RUN --format ply|gltf|particles|vtk|vdb|usd|usd-splats``: a reconstruction for other tools."""

from __future__ import annotations

import math
from pathlib import Path


def register(sub):
    p = sub.add_parser("export", help="write a reconstruction as 3DGS PLY or glTF, particle PLYs or VTK, OpenVDB or USD",
                       description="ply: the Gaussians at one time as a 3DGS-compatible PLY (x y z nx ny nz f_dc_* "
                                   "f_rest_* opacity scale_* rot_*), or one per frame with --frames. gltf: the same as binary glTF (.glb) "
                                   "with KHR_gaussian_splatting. particles: per "
                                   "frame a PLY of points with velocity (x y z vx vy vz radius opacity). vtk: the same points per "
                                   "frame as legacy VTK with a velocity vector (meshio / Blender's sequence loader: "
                                   "motion blur). vdb: per "
                                   "frame an OpenVDB density grid. usd: one USD file of points with a time sample "
                                   "per frame. usd-splats: one USD file of OpenUSD 3D Gaussian splats "
                                   "(ParticleField3DGaussianSplat) with a time sample per frame (pxr and openvdb "
                                   "come with the bpy module). Frames are the "
                                   "reconstruction's training frames, or a grid at --fps over its clip.")
    p.add_argument("run", type=Path, help="run folder (holding recon.h5) or a recon.h5 file")
    p.add_argument("--format", required=True, choices=["ply", "gltf", "particles", "vtk", "vdb", "usd", "usd-splats"],
                   help="what to write")
    p.add_argument("--time", type=float, default=None,
                   help="ply, gltf: seconds into the clip (default: the first frame); exclusive with --frames")
    p.add_argument("--frames", default=None,
                   help="START:END:STEP over the frames (default: every frame; ply, gltf: one file per frame)")
    p.add_argument("--fps", type=float, default=None,
                   help="frames on a grid at this rate over the clip instead of the training frames "
                        "(the decoder is continuous: 2x the source rate gives in-between frames)")
    p.add_argument("--out", type=Path, default=None,
                   help="output file (ply or gltf with --time, usd, usd-splats) or folder (default: RUN/export/...)")
    p.add_argument("--radius-scale", type=float, default=1.0,
                   help="particle radius = this x the geometric mean of its Gaussian scales (default 1)")
    p.add_argument("--sh-degree", type=int, default=3, choices=[0, 1, 2, 3],
                   help="ply: spherical-harmonic degree written (default 3, what the reference 3DGS reader and "
                        "most splat viewers expect: coefficients above the reconstruction's degree are zero; a "
                        "lower degree drops the view-dependent colour above it)")
    p.add_argument("--voxel", type=float, default=None, help="vdb voxel size in metres (default: half the median radius)")
    p.set_defaults(func=run)


def check_options(args) -> None:
    from gf_core.errors import InputError

    if args.time is not None and args.frames is not None:
        raise InputError("--time", "give --time or --frames, not both")
    if args.time is not None and args.format not in ("ply", "gltf"):
        raise InputError("--time", f"is for --format ply or gltf; {args.format} takes --frames")
    if args.time is not None and not math.isfinite(args.time):
        raise InputError("--time", f"must be a finite number of seconds, got {args.time}")
    if args.fps is not None and not (math.isfinite(args.fps) and args.fps > 0):
        raise InputError("--fps", f"must be > 0, got {args.fps}")
    if not (math.isfinite(args.radius_scale) and args.radius_scale > 0):
        raise InputError("--radius-scale", f"must be > 0, got {args.radius_scale}")
    if args.voxel is not None and not (math.isfinite(args.voxel) and args.voxel > 0):
        raise InputError("--voxel", f"must be > 0, got {args.voxel}")


def run(args) -> int:
    from gf_core.downstream import export as ex
    from gf_core.formats.decoder_np import ParticleAnimation
    from gf_core.errors import InputError
    from gf_core.formats.hdf5 import read_recon

    from .options import parse_frames

    check_options(args)
    recon_path = args.run / "recon.h5" if args.run.is_dir() else args.run
    if not recon_path.exists():
        raise InputError(recon_path, "no such reconstruction (run gf-cli reconstruct first)")
    recon = read_recon(recon_path)
    anim = ParticleAnimation(recon, source=str(recon_path))
    base = (args.run if args.run.is_dir() else args.run.parent) / "export"
    frames = parse_frames(args.frames) if args.frames is not None else None
    fmt = args.format
    if fmt in ("ply", "gltf") and args.frames is None:
        t = float(recon.time_min) if args.time is None else args.time
        suffix = {"ply": ".ply", "gltf": ".glb"}[fmt]
        out = args.out or base / f"gaussians_t{t:.4f}{suffix}"
        if out.exists() and out.is_dir():
            raise InputError(out, f"--out for a single {fmt} file must be a file path, and this is a folder")
        if fmt == "gltf" and out.suffix != ".glb":
            raise InputError(out, "--out for gltf must end in .glb (binary glTF)")
        if fmt == "ply":
            ex.export_ply(anim, t, out, sh_degree=args.sh_degree)
        else:
            ex.export_gltf(anim, t, out)
        print(f"wrote {out} ({anim.num_particles} Gaussians at t = {t:g} s)")
        return 0
    times = ex.export_times(recon, frames=frames, fps=args.fps)
    if fmt in ("usd", "usd-splats"):
        out = args.out or base / ("particles.usdc" if fmt == "usd" else "gaussians.usdc")
        if out.suffix not in (".usd", ".usdc", ".usda"):
            raise InputError(out, f"--out for {fmt} must end in .usd, .usdc or .usda")
        fps = args.fps or ex.sample_rate(times, (recon.config or {}).get("fps"), where=recon_path)
        if fmt == "usd":
            ex.export_usd(anim, times, out, fps=fps, radius_scale=args.radius_scale)
        else:
            ex.export_usd_splats(anim, times, out, fps=fps)
        what = "points" if fmt == "usd" else "Gaussians"
        print(f"wrote {out} ({len(times)} time samples at {fps:g} per second, {anim.num_particles} {what})")
        return 0
    out = args.out or base / {"ply": "ply", "gltf": "gltf", "particles": "particles", "vtk": "vtk", "vdb": "vdb"}[fmt]
    if out.exists() and not out.is_dir():
        raise InputError(out, f"--out for {fmt} is a folder (one file per frame), and this is a file")
    if fmt == "ply":
        files = [ex.export_ply(anim, t, out / f"gaussians_{k:05d}.ply", sh_degree=args.sh_degree)
                 for k, t in enumerate(times)]
    elif fmt == "gltf":
        files = [ex.export_gltf(anim, t, out / f"gaussians_{k:05d}.glb") for k, t in enumerate(times)]
    elif fmt == "particles":
        files = ex.export_particles(anim, times, out, radius_scale=args.radius_scale)
    elif fmt == "vtk":
        files = ex.export_vtk(anim, times, out, radius_scale=args.radius_scale)
    else:
        files = ex.export_vdb(anim, times, out, voxel=args.voxel, radius_scale=args.radius_scale)
    print(f"wrote {len(files)} files to {out} (times {times[0]:g} .. {times[-1]:g} s)")
    return 0
