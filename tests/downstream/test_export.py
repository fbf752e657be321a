"""gf-cli export: 3DGS PLY (reads back identical, renders the same image), particle PLYs with
velocities, OpenVDB (identical voxels), USD points (identical positions at every time sample) and
USD Gaussian splats (read back by OpenUSD 26's own schema)."""

import importlib.util

import numpy as np
import pytest
import torch

from gf_core.downstream import export as ex
from gf_core.formats.ply import ply_columns_to_gaussians, read_ply
from gf_core.camera import Camera
from gf_core.formats.decoder_np import ParticleAnimation
from gf_core.errors import FormatError, InputError
from gf_core.formats.hdf5 import ReconData, read_recon, write_recon
from gf_core.render import render
from gf_core.recon.decoder import Decoder, DecoderConfig

needs_bpy = pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="pxr/openvdb come with bpy")
TIMES = [0.0, 0.1, 0.2, 0.3]


@pytest.fixture(scope="module")
def recon_file(tmp_path_factory):
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n = 200
    dec = Decoder(n, DecoderConfig(hidden_width=64))
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.02)
    sh = rng.normal(0.0, 0.5, (n, 4, 3)).astype(np.float32)
    r = ReconData(means=rng.uniform(-0.2, 0.2, (n, 3)).astype(np.float32),
                  log_scales=rng.uniform(np.log(0.01), np.log(0.03), (n, 3)).astype(np.float32),
                  quats=rng.normal(size=(n, 4)).astype(np.float32), logit_opacity=rng.normal(1.0, 1.0, n).astype(np.float32),
                  sh=sh, time_min=0.0, time_max=0.3, decoder=dec.to_data(),
                  config={"frame_times_s": TIMES, "fps": 10.0,
                          "bounds": {"lo": [-0.5] * 3, "hi": [0.5] * 3, "log_scale_min": -9.0, "log_scale_max": -0.5}})
    path = tmp_path_factory.mktemp("run") / "recon.h5"
    write_recon(path, r)
    return path


def test_ply_reads_back_identical_and_renders_the_same_image(recon_file, tmp_path):
    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    t = 0.17
    path = ex.export_ply(anim, t, tmp_path / "g.ply")
    cols = read_ply(path)
    assert list(cols)[:6] == ["x", "y", "z", "nx", "ny", "nz"]
    # degree 3 by default (the reconstruction's is 1): 45 f_rest properties, the higher ones zero
    assert [k for k in cols if k.startswith("f_rest_")] == [f"f_rest_{j}" for j in range(45)]
    assert list(cols)[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    g = ply_columns_to_gaussians(cols)
    at = anim.at(t)
    np.testing.assert_array_equal(g["means"], at["positions"])
    np.testing.assert_array_equal(g["log_scales"], at["log_scales"])
    np.testing.assert_array_equal(g["quats"], at["quats"])
    np.testing.assert_array_equal(g["logit_opacity"], r.logit_opacity)
    assert g["sh"].shape == (r.num_particles, 16, 3)
    np.testing.assert_array_equal(g["sh"][:, :4], r.sh)
    assert not g["sh"][:, 4:].any()
    # the model's own degree on request
    own = ply_columns_to_gaussians(read_ply(ex.export_ply(anim, t, tmp_path / "g1.ply", sh_degree=None)))
    np.testing.assert_array_equal(own["sh"], r.sh)
    # as Gaussians in the renderer: the image of the reconstruction at t (torch decoder)
    from gf_core.recon.model import FluidModel

    model = FluidModel.from_recon(r)
    cam = Camera.look_at([0.0, -1.2, 0.3], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], fx=60.0, width=64, height=64)
    with torch.no_grad():
        ref = render(**model.at(t), camera=cam).color
    t_ = {k: torch.as_tensor(v) for k, v in g.items()}
    img = render(t_["means"], torch.exp(t_["log_scales"]), t_["quats"], torch.sigmoid(t_["logit_opacity"]),
                 t_["sh"], cam).color
    assert ref.abs().max() > 0.1
    torch.testing.assert_close(img, ref, atol=1e-4, rtol=0)


def reference_3dgs_load_ply(path, max_sh_degree=3):
    """The parsing of the reference 3DGS reader (graphdeco-inria gaussian-splatting,
    ``GaussianModel.load_ply``), with numpy in place of plyfile: the f_rest properties sorted by
    their index must number exactly 3 x (max_sh_degree + 1)^2 - 3, and are read channel-major."""
    el = read_ply(path)
    xyz = np.stack([el["x"], el["y"], el["z"]], 1)
    opacities = el["opacity"][:, None]
    dc = np.stack([el["f_dc_0"], el["f_dc_1"], el["f_dc_2"]], 1)[:, :, None]
    extra = sorted((k for k in el if k.startswith("f_rest_")), key=lambda x: int(x.split("_")[-1]))
    assert len(extra) == 3 * (max_sh_degree + 1) ** 2 - 3
    rest = np.zeros((len(xyz), len(extra)))
    for idx, k in enumerate(extra):
        rest[:, idx] = el[k]
    rest = rest.reshape(len(xyz), 3, (max_sh_degree + 1) ** 2 - 1)
    scales = np.stack([el[k] for k in sorted((k for k in el if k.startswith("scale_")), key=lambda x: int(x.split("_")[-1]))], 1)
    rots = np.stack([el[k] for k in sorted((k for k in el if k.startswith("rot")), key=lambda x: int(x.split("_")[-1]))], 1)
    # (N, 3, K) as the reference keeps them: features_dc (N, 1, 3) and features_rest (N, K - 1, 3) after transposes
    return {"xyz": xyz, "opacity": opacities, "features_dc": np.transpose(dc, (0, 2, 1)),
            "features_rest": np.transpose(rest, (0, 2, 1)), "scaling": scales, "rotation": rots}


def test_the_default_ply_loads_in_the_reference_3dgs_reader(recon_file, tmp_path):
    """The reference reader's default (sh_degree 3) loads the default export; every coefficient of
    the degree-1 reconstruction lands where the reader's renderer evaluates it, the rest zero.
    The reconstruction's own degree (9 f_rest) is refused by that reader, as it would be."""
    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    at = anim.at(0.1)
    ref = reference_3dgs_load_ply(ex.export_ply(anim, 0.1, tmp_path / "g.ply"))
    np.testing.assert_array_equal(ref["xyz"], at["positions"])
    np.testing.assert_array_equal(ref["features_dc"][:, 0], at["sh"][:, 0])
    np.testing.assert_array_equal(ref["features_rest"][:, :3], at["sh"][:, 1:4])
    assert ref["features_rest"].shape == (r.num_particles, 15, 3) and not ref["features_rest"][:, 3:].any()
    np.testing.assert_array_equal(ref["scaling"], at["log_scales"])
    np.testing.assert_array_equal(ref["rotation"], at["quats"])
    np.testing.assert_array_equal(ref["opacity"][:, 0], at["logit_opacity"])
    with pytest.raises(AssertionError):
        reference_3dgs_load_ply(ex.export_ply(anim, 0.1, tmp_path / "own.ply", sh_degree=None))
    # degree 0 drops the view-dependent terms: no f_rest at all
    zero = reference_3dgs_load_ply(ex.export_ply(anim, 0.1, tmp_path / "g0.ply", sh_degree=0), max_sh_degree=0)
    np.testing.assert_array_equal(zero["features_dc"][:, 0], at["sh"][:, 0])
    with pytest.raises(InputError, match="--sh-degree"):
        ex.export_ply(anim, 0.1, tmp_path / "g4.ply", sh_degree=4)


def test_ply_reader_refuses_bad_files(tmp_path):
    (tmp_path / "a.ply").write_bytes(b"not a ply")
    with pytest.raises(FormatError, match="a.ply"):
        read_ply(tmp_path / "a.ply")
    ex.write_ply(tmp_path / "b.ply", {"x": np.arange(10.0)})
    raw = (tmp_path / "b.ply").read_bytes()
    (tmp_path / "c.ply").write_bytes(raw[:-8])
    with pytest.raises(FormatError, match="truncated"):
        read_ply(tmp_path / "c.ply")
    with pytest.raises(FormatError, match="not a 3DGS PLY"):
        ply_columns_to_gaussians(read_ply(tmp_path / "b.ply"))


def test_particle_plys_carry_decoder_velocities(recon_file, tmp_path):
    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    files = ex.export_particles(anim, ex.export_times(r), tmp_path)
    assert [f.name for f in files] == [f"particles_{k:05d}.ply" for k in range(4)]
    dec = Decoder.from_data(r.decoder)
    cols = read_ply(files[2])
    with torch.no_grad():
        vp = dec(TIMES[2] / 0.3, with_velocity=True)["vp"].numpy() / 0.3
    v = np.stack([cols["vx"], cols["vy"], cols["vz"]], 1)
    assert np.sum(np.abs(v - vp).max(1) > 1e-4) <= 1
    # --fps resamples the clip: 2x the source rate gives the in-between times too
    assert ex.export_times(r, fps=20.0) == pytest.approx(list(np.arange(7) * 0.05))
    assert ex.export_times(r, frames=slice(1, None, 2)) == [0.1, 0.3]


def test_vtk_particles_carry_a_velocity_vector_through_meshio(recon_file, tmp_path):
    """The per-frame VTK points read by meshio (what Blender's sequence loader and ParaView
    scripts use): positions, a velocity *vector* (motion blur needs one, which no PLY reader
    gives), radius and opacity, equal to the numpy decoder's values."""
    import meshio

    from gf_cli.main import main

    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    assert main(["export", str(recon_file), "--format", "vtk", "--out", str(tmp_path / "vtk")]) == 0
    files = sorted((tmp_path / "vtk").glob("particles_*.vtk"))
    assert [f.name for f in files] == [f"particles_{k:05d}.vtk" for k in range(4)]
    for k, t in enumerate(TIMES):
        m = meshio.read(files[k])
        g = anim.at(t, velocity=True)
        assert m.point_data["velocity"].shape == (200, 3)
        np.testing.assert_allclose(m.points, g["positions"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(m.point_data["velocity"], g["velocities"], rtol=0, atol=1e-5)
        np.testing.assert_allclose(m.point_data["opacity"].reshape(-1), g["opacities"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(m.point_data["radius"].reshape(-1), ex.particle_radii(g["log_scales"]), rtol=1e-6)
        assert m.cells[0].type == "vertex" and len(m.cells[0].data) == 200
    assert np.abs(meshio.read(files[2]).point_data["velocity"]).max() > 1e-3


@needs_bpy
def test_vdb_reads_back_identical_voxels(recon_file, tmp_path):
    from gf_core.formats.caches import density_grid, read_vdb_density

    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    files = ex.export_vdb(anim, [0.1], tmp_path, voxel=0.02)
    g = anim.at(0.1)
    dense, _ = density_grid(g["positions"], ex.particle_radii(g["log_scales"]), anim.opacity, 0.02)
    back = read_vdb_density(files[0], dense.shape)
    np.testing.assert_array_equal(back, dense)
    assert dense.max() > 0.5


@needs_bpy
def test_usd_reads_back_identical_positions(recon_file, tmp_path):
    from gf_core.formats.caches import read_usd_points

    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    path = ex.export_usd(anim, TIMES, tmp_path / "p.usdc", fps=10.0)
    for k, t in enumerate(TIMES):
        # float32 in the file; 1e-6 m allows only the last bit of a second evaluation (numpy's
        # matrix products need not repeat bit for bit between calls), not a lossy conversion
        np.testing.assert_allclose(read_usd_points(path, k), anim.at(t)["positions"], rtol=0, atol=1e-6)



def _unit_wxyz(q):
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)  # q and -q are one rotation


@needs_bpy
def test_usd_splats_hold_every_gaussian_as_the_schema_defines(recon_file, tmp_path, capsys):
    """OpenUSD's ParticleField3DGaussianSplat: linear scales (exp of the log scales), unit
    quaternions, opacities in [0, 1], the SH coefficients (degree + 1)^2 per particle in the 3DGS
    order, a time sample per exported frame at the clip's real rate."""
    from gf_cli.main import main
    from gf_core.formats.caches import bundled_module

    bundled_module("pxr")
    from pxr import Usd

    anim = ParticleAnimation(read_recon(recon_file))
    out = tmp_path / "g.usda"
    assert main(["export", str(recon_file), "--format", "usd-splats", "--out", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(10.0)
    prim = stage.GetPrimAtPath("/gaussfluids/gaussians")
    assert prim.GetTypeName() == "ParticleField3DGaussianSplat"
    assert prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get() == 1
    for k, t in enumerate(TIMES):
        g = anim.at(t)
        get = lambda name: np.asarray(prim.GetAttribute(name).Get(k), np.float64)  # noqa: E731
        np.testing.assert_allclose(get("positions"), g["positions"], atol=1e-6)
        np.testing.assert_allclose(get("scales"), np.exp(g["log_scales"]), rtol=1e-6)
        xyzw = np.array([[q.GetImaginary()[0], q.GetImaginary()[1], q.GetImaginary()[2], q.GetReal()]
                         for q in prim.GetAttribute("orientations").Get(k)])
        np.testing.assert_allclose(_unit_wxyz(xyzw[:, [3, 0, 1, 2]]), _unit_wxyz(g["quats"]), atol=1e-6)
        np.testing.assert_allclose(get("opacities"), g["opacities"], atol=1e-6)
        np.testing.assert_allclose(get("radiance:sphericalHarmonicsCoefficients"), g["sh"].reshape(-1, 3), atol=1e-6)
        np.testing.assert_allclose(get("primvars:displayOpacity"), g["opacities"], atol=1e-6)
        lo, hi = get("extent")
        assert np.all(lo <= g["positions"].min(0)) and np.all(hi >= g["positions"].max(0))
    assert main(["export", str(recon_file), "--format", "usd-splats", "--out", str(tmp_path / "g.ply")]) == 2
    assert "--out for usd-splats must end in .usd, .usdc or .usda" in capsys.readouterr().err


USD_CORE = "usd-core==26.11"  # the first OpenUSD on PyPI with ParticleField3DGaussianSplat is 26.03

READ_SPLATS = """
import json, sys
from pxr import Usd, UsdVol
stage = Usd.Stage.Open(sys.argv[1])
prim = stage.GetPrimAtPath("/gaussfluids/gaussians")
splat = UsdVol.ParticleField3DGaussianSplat(prim)
sh_api = UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI(prim)
print(json.dumps({
    "version": list(Usd.GetVersion()),
    "is_a": prim.IsA(UsdVol.ParticleField3DGaussianSplat),
    "apis": [prim.HasAPI(a) for a in (UsdVol.ParticleFieldPositionAttributeAPI, UsdVol.ParticleFieldOrientationAttributeAPI,
                                      UsdVol.ParticleFieldScaleAttributeAPI, UsdVol.ParticleFieldOpacityAttributeAPI,
                                      UsdVol.ParticleFieldKernelGaussianEllipsoidAPI,
                                      UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI)],
    "degree": sh_api.GetRadianceSphericalHarmonicsDegreeAttr().Get(),
    "positions": [list(p) for p in splat.GetPositionsAttr().Get(1)],
    "scales": [list(s) for s in splat.GetScalesAttr().Get(1)],
    "orientations": [[q.GetReal(), *q.GetImaginary()] for q in splat.GetOrientationsAttr().Get(1)],
    "opacities": list(splat.GetOpacitiesAttr().Get(1)),
    "sh": [list(c) for c in sh_api.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(1)],
}))
"""


def _usd_core(tmp_path_factory) -> str:
    """usd-core from PyPI, unpacked once into the wheel cache (the reference reader of the schema;
    kept out of the test process, whose pxr is Blender's)."""
    import os
    import subprocess
    import sys
    import zipfile
    from pathlib import Path

    cache = Path(os.environ.get("GF_WHEEL_CACHE", Path.home() / ".cache" / "gaussfluids" / "wheels"))
    target = cache / USD_CORE.replace("==", "-")
    if not (target / "pxr" / "UsdVol").is_dir():
        cache.mkdir(parents=True, exist_ok=True)
        r = subprocess.run([sys.executable, "-m", "pip", "download", USD_CORE, "--no-deps", "--only-binary=:all:",
                            "-d", str(cache), "--disable-pip-version-check", "--quiet"], capture_output=True, text=True)
        wheels = sorted(cache.glob(f"{USD_CORE.replace('==', '-').replace('-', '_', 1)}-*.whl"))
        assert r.returncode == 0 and wheels, f"pip download {USD_CORE} failed: {r.stderr[-500:]}"
        tmp = Path(tmp_path_factory.mktemp("usd_core"))
        with zipfile.ZipFile(wheels[-1]) as z:
            z.extractall(tmp)
        os.replace(tmp, target) if not target.exists() else None
    return str(target)


@needs_bpy
def test_usd_splats_read_by_openusd_26_as_the_typed_schema(recon_file, tmp_path, tmp_path_factory):
    """The file read by the schema's own reader (usd-core 26.11, in its own process): the prim is a
    ParticleField3DGaussianSplat with its six built-in APIs, and the schema's getters return the
    Gaussians at a time code."""
    import json
    import os
    import subprocess
    import sys

    anim = ParticleAnimation(read_recon(recon_file))
    out = ex.export_usd_splats(anim, TIMES, tmp_path / "g.usdc", fps=10.0)
    env = dict(os.environ, PYTHONPATH=_usd_core(tmp_path_factory))
    r = subprocess.run([sys.executable, "-c", READ_SPLATS, str(out)], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout)
    assert got["version"][1] >= 26 and got["is_a"] and all(got["apis"]) and got["degree"] == 1
    g = anim.at(TIMES[1])
    np.testing.assert_allclose(got["positions"], g["positions"], atol=1e-6)
    np.testing.assert_allclose(got["scales"], np.exp(g["log_scales"]), rtol=1e-6)
    np.testing.assert_allclose(_unit_wxyz(got["orientations"]), _unit_wxyz(g["quats"]), atol=1e-6)
    np.testing.assert_allclose(got["opacities"], g["opacities"], atol=1e-6)
    assert len(got["sh"]) == len(g["positions"]) * 4
    np.testing.assert_allclose(got["sh"], g["sh"].reshape(-1, 3), atol=1e-6)

@needs_bpy
def test_usd_points_carry_colour_opacity_kind_and_the_real_frame_rate(recon_file, tmp_path):
    """What DCC tools read besides positions: displayColor / displayOpacity per point (else grey
    points), kind = component on the default prim, and time codes per second such that the cache
    plays in real time (the exported frames 0.1 s apart: 10; every other one: 5)."""
    from gf_cli.main import main
    from gf_core.formats.caches import bundled_module

    bundled_module("pxr")
    from pxr import Usd, UsdGeom

    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    out = tmp_path / "p.usda"
    assert main(["export", str(recon_file), "--format", "usd", "--out", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    assert Usd.ModelAPI(stage.GetDefaultPrim()).GetKind() == "component"
    assert stage.GetTimeCodesPerSecond() == pytest.approx(10.0)
    pts = UsdGeom.Points(stage.GetPrimAtPath("/gaussfluids/particles"))
    api = UsdGeom.PrimvarsAPI(pts)
    col, opa = api.GetPrimvar("displayColor"), api.GetPrimvar("displayOpacity")
    assert col.GetInterpolation() == "vertex" and opa.GetInterpolation() == "vertex"
    for k, t in enumerate(TIMES):
        at = anim.at(t)
        np.testing.assert_allclose(np.asarray(col.Get(k)), np.clip(at["colors"], 0, 1), atol=1e-6)
        np.testing.assert_allclose(np.asarray(opa.Get(k)), at["opacities"], atol=1e-6)
    assert at["colors"].std() > 0.05  # not one grey
    assert main(["export", str(recon_file), "--format", "usd", "--frames", "::2", "--out", str(tmp_path / "h.usda")]) == 0
    assert Usd.Stage.Open(str(tmp_path / "h.usda")).GetTimeCodesPerSecond() == pytest.approx(5.0)
    # unevenly spaced frames have no one rate: asked for --fps
    with pytest.raises(InputError, match="--fps"):
        ex.sample_rate([0.0, 0.1, 0.3], where="r.h5")
    assert ex.sample_rate([0.5]) == 30.0 and ex.sample_rate([0.5], 24.0) == 24.0


@needs_bpy
def test_vdb_density_is_a_fog_volume(recon_file, tmp_path):
    from gf_core.formats.caches import bundled_module

    vdb = bundled_module("openvdb")
    files = ex.export_vdb(ParticleAnimation(read_recon(recon_file)), [0.1], tmp_path, voxel=0.02)
    grid = vdb.read(str(files[0]), "density")
    assert grid.gridClass == vdb.GridClass.FOG_VOLUME == "fog volume"


@needs_bpy
def test_cli_export_every_format(recon_file, tmp_path, capsys):
    from gf_cli.main import main

    run = recon_file.parent
    assert main(["export", str(run), "--format", "ply", "--time", "0.05", "--out", str(tmp_path / "g.ply")]) == 0
    assert (tmp_path / "g.ply").exists()
    assert main(["export", str(recon_file), "--format", "particles", "--frames", "0:4:2", "--out", str(tmp_path / "p")]) == 0
    assert sorted(f.name for f in (tmp_path / "p").iterdir()) == ["particles_00000.ply", "particles_00001.ply"]
    assert main(["export", str(run), "--format", "vdb", "--frames", "0:1", "--out", str(tmp_path / "v")]) == 0
    assert main(["export", str(run), "--format", "usd", "--fps", "20", "--out", str(tmp_path / "u.usda")]) == 0
    assert "7 time samples" in capsys.readouterr().out
    # options checked with a message naming them
    for bad, msg in ((["--format", "usd", "--time", "0.1"], "--time"), (["--format", "ply", "--fps", "0"], "--fps"),
                     (["--format", "usd", "--out", str(tmp_path / "x.txt")], "usd"),
                     (["--format", "vdb", "--frames", "9:"], "--frames")):
        assert main(["export", str(run), *bad]) == 2
        assert msg in capsys.readouterr().err


@needs_bpy
def test_exported_velocities_reach_the_next_sample(tmp_path):
    """Velocities in the caches agree with the positions: a splash-like motion (free fall at
    2-3 m/s, a sideways drift and a small smooth wobble from Phi), decoded with the default C1
    joins (Hermite residuals, Phi at the knots), exported at twice the training rate: p + v dt
    lands within 10% of the step from the next sample in the USD cache and the particle PLYs."""
    from gf_core.formats.caches import bundled_module

    bundled_module("pxr")
    from pxr import Usd, UsdGeom

    n, frames, dt = 64, 16, 1.0 / 30
    times = np.arange(frames) * dt
    knots = times / times[-1]
    torch.manual_seed(5)
    dec = Decoder(n, DecoderConfig(residuals=True, residual_interpolation="hermite", time_interpolation="knots",
                                   hidden_width=32, n_freqs=2), knots=knots)
    rng = np.random.default_rng(5)
    v0 = np.stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-2.5, -2.0, n)], 1)
    fall = v0[:, None, :] * times[None, :, None] + 0.5 * np.array([0, 0, -9.81]) * times[None, :, None] ** 2
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.002)  # Phi: a small smooth wobble on top
        dec.residual_dp.copy_(torch.as_tensor(fall, dtype=torch.float32))
    r = ReconData(means=rng.uniform(-0.1, 0.1, (n, 3)).astype(np.float32),
                  log_scales=np.full((n, 3), np.log(0.01), np.float32),
                  quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32), logit_opacity=np.zeros(n, np.float32),
                  sh=rng.normal(0.0, 0.5, (n, 1, 3)).astype(np.float32), time_min=0.0, time_max=float(times[-1]),
                  decoder=dec.to_data(), config={"frame_times_s": times.tolist(), "fps": 30.0})
    write_recon(tmp_path / "r.h5", r)
    anim = ParticleAnimation(read_recon(tmp_path / "r.h5"))
    t_out = ex.export_times(r, fps=60.0)
    path = ex.export_usd(anim, t_out, tmp_path / "p.usdc", fps=60.0)
    stage = Usd.Stage.Open(str(path))
    pts = UsdGeom.Points(stage.GetPrimAtPath("/gaussfluids/particles"))
    p = np.stack([np.asarray(pts.GetPointsAttr().Get(Usd.TimeCode(k))) for k in range(len(t_out))])
    v = np.stack([np.asarray(pts.GetVelocitiesAttr().Get(Usd.TimeCode(k))) for k in range(len(t_out))])
    plys = [read_ply(f) for f in ex.export_particles(anim, t_out, tmp_path / "ply")]
    v_ply = np.stack([np.stack([c["vx"], c["vy"], c["vz"]], 1) for c in plys])
    np.testing.assert_allclose(v_ply, v, rtol=0, atol=1e-5)
    h = t_out[1] - t_out[0]
    step = np.linalg.norm(p[1:] - p[:-1], axis=2)
    miss = np.linalg.norm(p[:-1] + v[:-1] * h - p[1:], axis=2)
    assert step.min() > 0.02  # the particles do move: 2-4 cm per sample
    assert (miss / step).max() < 0.10, (miss / step).max()


def read_glb(path):
    """A strict reader of binary glTF 2.0 as the spec lays it out: (JSON document, {attribute: array})."""
    import json
    import struct

    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert magic == 0x46546C67 and version == 2 and length == len(data)
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A and jlen % 4 == 0
    doc = json.loads(data[20:20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942 and blen % 4 == 0 and 28 + jlen + blen == len(data)
    blob = data[28 + jlen:]
    assert doc["buffers"][0]["byteLength"] <= blen and "uri" not in doc["buffers"][0]
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
    prim = doc["meshes"][doc["nodes"][doc["scenes"][doc["scene"]]["nodes"][0]]["mesh"]]["primitives"][0]
    out = {}
    for name, k in prim["attributes"].items():
        acc = doc["accessors"][k]
        view = doc["bufferViews"][acc["bufferView"]]
        assert acc["componentType"] == 5126 and view["byteOffset"] % 4 == 0
        w = widths[acc["type"]]
        assert view["byteLength"] == acc["count"] * w * 4
        out[name] = np.frombuffer(blob, "<f4", acc["count"] * w, view["byteOffset"]).reshape(acc["count"], w)
    return doc, prim, out


def test_gltf_gaussians_follow_khr_gaussian_splatting(recon_file, tmp_path):
    """The .glb export read back by the spec's layout: a POINTS primitive with the extension's
    attributes holding the decoded Gaussians (log scales, unit x y z w quaternions, opacities in
    [0, 1], every SH coefficient of the model's degree in the 3DGS order), POSITION min/max,
    COLOR_0 the base colour, the extension listed as used, and a node turning z-up into y-up."""
    from gf_cli.main import main

    r = read_recon(recon_file)
    anim = ParticleAnimation(r)
    out = tmp_path / "g.glb"
    assert main(["export", str(recon_file), "--format", "gltf", "--time", "0.1", "--out", str(out)]) == 0
    doc, prim, a = read_glb(out)
    ext = "KHR_gaussian_splatting"
    assert doc["asset"]["version"] == "2.0" and ext in doc["extensionsUsed"]
    assert prim["mode"] == 0 and prim["extensions"][ext]["kernel"] == "ellipse"
    assert prim["extensions"][ext]["colorSpace"] == "srgb_rec709_display"
    g = anim.at(0.1)
    np.testing.assert_allclose(a["POSITION"], g["positions"], atol=1e-7)
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose([acc["min"], acc["max"]], [g["positions"].min(0), g["positions"].max(0)], atol=1e-6)
    np.testing.assert_allclose(a[f"{ext}:SCALE"], g["log_scales"], atol=1e-7)
    q = g["quats"] / np.linalg.norm(g["quats"], axis=1, keepdims=True)
    np.testing.assert_allclose(a[f"{ext}:ROTATION"], q[:, [1, 2, 3, 0]], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(a[f"{ext}:ROTATION"], axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(a[f"{ext}:OPACITY"][:, 0], g["opacities"], atol=1e-6)
    k = g["sh"].shape[1]
    assert k == 4 and sorted(n for n in a if ":SH_DEGREE_" in n) == sorted(
        [f"{ext}:SH_DEGREE_0_COEF_0"] + [f"{ext}:SH_DEGREE_1_COEF_{m}" for m in range(3)])
    for ell, m in ((0, 0), (1, 0), (1, 1), (1, 2)):
        np.testing.assert_allclose(a[f"{ext}:SH_DEGREE_{ell}_COEF_{m}"], g["sh"][:, ell * ell + m], atol=1e-7)
    np.testing.assert_allclose(a["COLOR_0"][:, :3], g["colors"], atol=1e-6)
    rot = doc["nodes"][0]["rotation"]  # x y z w: -90 degrees about x takes +z (up) to +y (glTF's up)
    x, y, z, w = rot
    up = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    np.testing.assert_allclose(up, [0, 1, 0], atol=1e-12)
    # one file per frame with --frames
    assert main(["export", str(recon_file), "--format", "gltf", "--frames", "0:4:2", "--out", str(tmp_path / "f")]) == 0
    assert sorted(f.name for f in (tmp_path / "f").iterdir()) == ["gaussians_00000.glb", "gaussians_00001.glb"]
    assert main(["export", str(recon_file), "--format", "gltf", "--out", str(tmp_path / "x.gltf")]) == 2
