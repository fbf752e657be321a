"""The splatting renderer: gradients (gradcheck), native vs reference, robustness, fallback."""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gf_core.camera import Camera
from gf_core.errors import InputError
from gf_core.render import constants, native, render

needs_native = pytest.mark.skipif(not native.available(), reason="native backend did not build")
BACKENDS = ["reference", pytest.param("native", marks=needs_native)]


def cam(W=40, H=30, fx=40.0):
    return Camera.look_at([0.3, -3.0, 0.5], [0, 0, 0], [0, 0, 1], fx=fx, width=W, height=H)


def scene(n, *, dtype=torch.float64, degree=1, channels=3, seed=0, spread=1.2, log_scale=-2.3):
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * spread,
            torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.3 + log_scale),
            torch.randn(n, 4, generator=g, dtype=dtype),
            torch.rand(n, generator=g, dtype=dtype) * 0.7 + 0.1,
            torch.randn(n, (degree + 1) ** 2, channels, generator=g, dtype=dtype) * 0.3]


def run(params, camera, backend, *, grad=True, seed=3, **kw):
    ps = [p.detach().clone().requires_grad_(grad) for p in params]
    channels = params[4].shape[2]
    out = render(*ps, camera, background=torch.full((channels,), 0.25, dtype=params[0].dtype),
                 backend=backend, return_depth=True, **kw)
    if grad:
        g = torch.Generator().manual_seed(seed)
        # the loss weights are drawn in float32 so that float32 and float64 runs share them
        w = torch.randn(out.color.shape, generator=g, dtype=torch.float32).to(out.color.dtype)
        loss = (out.color * w).sum() + (out.alpha ** 2).sum() + 0.1 * out.depth.sum()
        loss.backward()
    return out, ps


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("degree, channels", [(0, 1), (1, 3), (3, 3)])
def test_gradcheck(backend, degree, channels):
    camera = cam(18, 14, fx=25.0)
    params = scene(5, degree=degree, channels=channels, seed=degree, spread=0.8, log_scale=-1.8)
    bg = torch.full((channels,), 0.2, dtype=torch.float64)

    def f(*args):
        o = render(*args, camera, background=bg, backend=backend, return_depth=True)
        return o.color, o.alpha, o.depth

    args = [p.clone().requires_grad_(True) for p in params]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def rel_err(a, b):
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


def rel_norm(a, b):
    a, b = a.detach().double(), b.detach().double()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@needs_native
@pytest.mark.parametrize("n, W, H, degree, channels", [
    (60, 33, 17, 0, 1), (400, 64, 48, 1, 3), (3000, 97, 80, 2, 3), (1500, 128, 128, 3, 1)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_matches_reference(n, W, H, degree, channels, dtype):
    """float64: the backends agree to 1e-10 everywhere. float32: outputs agree to 1e-4 of their
    scale; gradients (sums over many pixels, with cancellation) agree to 1e-4 in norm, and each is
    within 1e-4 (norm) of the float64 result for the same inputs."""
    camera = cam(W, H, fx=0.8 * W)
    params = scene(n, dtype=dtype, degree=degree, channels=channels, seed=n,
                   log_scale=math.log(0.4 / n ** (1 / 3)))
    ref, ps_ref = run(params, camera, "reference")
    nat, ps_nat = run(params, camera, "native")
    assert torch.equal(ref.radii, nat.radii)
    grads = [(nat.means2d.grad, ref.means2d.grad, "means2d")] + \
        [(pn.grad, pr.grad, f"param {i}") for i, (pn, pr) in enumerate(zip(ps_nat, ps_ref))]
    m = ref.alpha > 1e-2  # depth is a ratio (accumulated depth / alpha): compare where not empty
    if dtype == torch.float64:
        for a, b, name in [(nat.color, ref.color, "color"), (nat.alpha, ref.alpha, "alpha"),
                           (nat.depth[m], ref.depth[m], "depth")] + grads:
            assert rel_err(a, b) < 1e-10, (name, rel_err(a, b))
        return
    for a, b, name in [(nat.color, ref.color, "color"), (nat.alpha, ref.alpha, "alpha")]:
        assert rel_err(a, b) < 1e-4, (name, rel_err(a, b))
    assert rel_err(nat.depth[m], ref.depth[m]) < 1e-3
    truth = run([p.double() for p in params], camera, "reference")[1]
    for (a, b, name), pt in zip(grads[1:], truth):
        assert rel_norm(a, b) < 1e-4, (name, rel_norm(a, b))
        assert rel_norm(a, pt.grad) < 1e-4 and rel_norm(b, pt.grad) < 1e-4, name
    assert rel_norm(*grads[0][:2]) < 1e-4


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_gaussian_matches_ewa_formula(backend):
    """An isotropic Gaussian of std s at depth z: alpha(pixel) = o exp(-d^2 / (2 (f^2 s^2/z^2 + 0.3)))."""
    camera = Camera(fx=50.0, fy=50.0, cx=16.0, cy=16.0, width=32, height=32)
    s, z, o = 0.05, 2.0, 0.6
    p = [torch.tensor([[0.0, 0.0, z]]), torch.full((1, 3), s), torch.tensor([[1.0, 0, 0, 0]]),
         torch.tensor([o]), torch.full((1, 1, 3), 1.0)]
    out = render(*p, camera, backend=backend)
    var = (50.0 * s / z) ** 2 + constants.LOW_PASS
    v, u = torch.meshgrid(torch.arange(32) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    expect = o * torch.exp(-((u - 16) ** 2 + (v - 16) ** 2) / (2 * var))
    expect = torch.where(expect >= constants.DEFAULT_MIN_ALPHA, expect, torch.zeros_like(expect))
    assert torch.allclose(out.alpha, expect, atol=1e-6)
    colour = constants.SH_C0 * 1.0 + 0.5
    assert torch.allclose(out.color, expect[..., None] * colour, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_faint_particle_not_erased(backend):
    # the particle projects onto the centre of pixel (16, 16)
    camera = Camera(fx=50.0, fy=50.0, cx=16.5, cy=16.5, width=32, height=32)
    p = [torch.tensor([[0.0, 0.0, 2.0]]), torch.full((1, 3), 0.01), torch.tensor([[1.0, 0, 0, 0]]),
         torch.tensor([0.01]), torch.zeros(1, 1, 1)]
    out = render(*p, camera, backend=backend)
    assert out.alpha.max() > 0.009
    # a raised threshold does erase it
    assert render(*p, camera, backend=backend, min_alpha=0.02).alpha.max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_and_alpha(backend):
    """Two opaque-ish sheets: expected depth lies between them, front sheet dominates."""
    camera = Camera(fx=40.0, fy=40.0, cx=16.0, cy=16.0, width=32, height=32)
    g = torch.Generator().manual_seed(0)
    xy = (torch.rand(400, 2, generator=g) - 0.5) * 2.0
    means = torch.cat([torch.cat([xy[:200], torch.full((200, 1), 3.0)], 1),
                       torch.cat([xy[200:], torch.full((200, 1), 5.0)], 1)])
    p = [means, torch.full((400, 3), 0.15), torch.tensor([[1.0, 0, 0, 0]]).repeat(400, 1),
         torch.full((400,), 0.9), torch.zeros(400, 1, 3)]
    out = render(*p, camera, backend=backend, return_depth=True)
    centre = out.depth[8:24, 8:24]
    assert out.alpha[8:24, 8:24].min() > 0.99
    assert (centre > 2.9).all() and (centre < 3.5).all()
    assert render(*p, camera, backend=backend).depth is None  # not requested, not rendered


def extreme_scene(dtype=torch.float32):
    """Every kind of trouble in one scene."""
    rows = []
    def add(mean, scale, quat, op):
        rows.append((mean, scale, quat, op))
    add([0, 0, 0], [0.05] * 3, [1, 0, 0, 0], 0.5)                 # ordinary
    add([0, -3.0, 0.5], [0.05] * 3, [1, 0, 0, 0], 0.5)            # at the camera centre
    add([0, -3.005, 0.5], [0.05] * 3, [1, 0, 0, 0], 0.5)          # inside the near plane
    add([0, -5.0, 0.5], [0.5] * 3, [1, 0, 0, 0], 0.5)             # behind the camera
    add([0.1, 0, 0], [1e-6] * 3, [1, 0, 0, 0], 0.5)               # tiny
    add([0, 1, 0], [1e3] * 3, [1, 0, 0, 0], 0.3)                  # huge (camera inside it)
    add([0.2, 0, 0.1], [1.0, 1e-4, 1e-4], [0.3, 0.2, 0.1, 0.9], 0.5)  # anisotropy 1e4
    add([0.2, 0.3, 0.1], [10.0, 1e-3, 1e-3], [0.9, 0.1, 0.4, 0.2], 0.5)
    add([-0.2, 0, 0], [0.05] * 3, [0, 0, 0, 0], 0.5)              # zero quaternion
    add([-0.3, 0, 0], [0.05] * 3, [1e3, 2e3, -5e2, 1e2], 0.5)     # unnormalised quaternion
    add([0, 0, 0.2], [0.05] * 3, [1, 0, 0, 0], 0.0)               # zero opacity
    add([0, 0.1, 0.2], [0.05] * 3, [1, 0, 0, 0], 1.0)             # saturated opacity
    add([30.0, 0, 0], [0.05] * 3, [1, 0, 0, 0], 0.5)              # far outside the frustum
    add([0.5, -2.9, 0.5], [0.02] * 3, [1, 0, 0, 0], 0.5)          # just in front, off-axis
    means, scales, quats, ops = (torch.tensor([r[i] for r in rows], dtype=dtype) for i in range(4))
    sh = torch.randn(len(rows), 4, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    return [means, scales, quats, ops, sh]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_inputs_stay_finite(backend, dtype):
    out, ps = run(extreme_scene(dtype), cam(48, 40), backend)
    for t in [out.color, out.alpha, out.depth, out.means2d] + [p.grad for p in ps]:
        assert torch.isfinite(t).all()
    assert out.radii[1:4].eq(0).all()  # at / inside near plane / behind: not drawn
    assert all(p.grad[1:4].abs().sum() == 0 for p in ps)
    assert out.radii[0] > 0 and out.radii[5] > 0 and out.radii[11] > 0
    assert out.radii[10] == 0 and out.radii[12] == 0  # zero opacity, off screen


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_and_all_culled(backend):
    camera = cam()
    empty = [torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0), torch.zeros(0, 1, 3)]
    out = render(*empty, camera, background=torch.tensor([0.1, 0.2, 0.3]), backend=backend)
    assert out.color.shape == (30, 40, 3) and torch.allclose(out.color, torch.tensor([0.1, 0.2, 0.3]))
    assert out.alpha.abs().max() == 0
    behind = scene(20, dtype=torch.float32)
    behind[0] = behind[0] + torch.tensor([0.0, -10.0, 0.0])  # all behind the camera
    o, ps = run(behind, camera, backend)
    assert o.alpha.abs().max() == 0 and all(torch.count_nonzero(p.grad) == 0 for p in ps)


@pytest.mark.parametrize("backend", BACKENDS)
def test_means2d_gradient_exposed(backend):
    params = scene(50, dtype=torch.float32)
    out, ps = run(params, cam(), backend)
    g = out.means2d.grad
    assert g is not None and g.shape == (50, 2)
    vis = out.radii > 0
    assert g[vis].abs().sum(1).gt(0).float().mean() > 0.9 and g[~vis].abs().sum() == 0


def test_bad_inputs():
    p = scene(4, dtype=torch.float32)
    bad = [t.clone() for t in p]
    bad[0][1, 2] = float("nan")
    with pytest.raises(InputError, match="means contains NaN"):
        render(*bad, cam())
    with pytest.raises(InputError, match="scales must have shape"):
        render(p[0], p[1][:3], *p[2:], cam())
    with pytest.raises(InputError, match="opacities must lie in"):
        render(*p[:3], p[3] + 2, p[4], cam())
    with pytest.raises(InputError, match="sh must have shape"):
        render(*p[:4], torch.zeros(4, 5, 3), cam())
    with pytest.raises(ValueError, match="unknown renderer backend 'magic'"):
        render(*p, cam(), backend="magic")
    with pytest.raises(InputError, match="background has 2 values for 3 channels"):
        render(*p, cam(), background=[0.0, 0.0])


def test_constants_shared_with_native_header():
    from gf_core import native as ext

    header = (ext.CSRC / "render" / "gaussian_math.h").read_text()
    named = [("kLowPass", constants.LOW_PASS), ("kAlphaMax", constants.ALPHA_MAX),
             ("kTransmittanceMin", constants.TRANSMITTANCE_MIN), ("kFrustumSlack", constants.FRUSTUM_SLACK),
             ("kShC0", constants.SH_C0), ("kShC1", constants.SH_C1)]
    named += [(f"kShC2_{i}", v) for i, v in enumerate(constants.SH_C2)]
    named += [(f"kShC3_{i}", v) for i, v in enumerate(constants.SH_C3)]
    for name, value in named:
        m = re.search(rf"{name} = ([-0-9.e]+)[;,]", header)
        assert m and float(m.group(1)) == value, name
    if native.available():  # and the values compiled into the extension
        assert native.load().constants() == [v for _, v in named]


def test_fallback_without_compiler(tmp_path):
    code = ("import warnings, torch\n"
            "from gf_core.render import render\n"
            "from gf_core.camera import Camera\n"
            "c = Camera.look_at([0,-3,0],[0,0,0],[0,0,1], fx=20, width=16, height=16)\n"
            "o = render(torch.zeros(1,3), torch.full((1,3),0.1), torch.tensor([[1.,0,0,0]]),"
            " torch.tensor([0.5]), torch.zeros(1,1,3), c)\n"
            "print('BACKEND', o.backend, float(o.alpha.max()) > 0)\n")
    env = dict(os.environ, CXX="/nonexistent/c++", GF_EXT_DIR=str(tmp_path), PYTHONWARNINGS="default")
    env.pop("GF_REQUIRE_NATIVE", None)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "BACKEND reference True" in r.stdout
    warn = [ln for ln in r.stderr.splitlines() if "native extension unavailable" in ln]
    assert len(warn) == 1 and "using the pure-torch reference" in r.stderr
    # the same failure is an error where the native build is required (CI, make test)
    env["GF_REQUIRE_NATIVE"] = "1"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode != 0 and "must build here" in r.stderr


def test_compiler_diagnostic_reaches_the_user(tmp_path):
    """A syntax error in a source gives the compiler's own message, not torch's command line."""
    import shutil

    from gf_core import native as nat

    src = tmp_path / "csrc"
    shutil.copytree(nat.CSRC, src)
    bad = (src / "render" / "render_cpu.cpp").read_text().replace("namespace gf {", "namespace gf { int broken = ;", 1)
    (src / "render" / "render_cpu.cpp").write_text(bad)
    code = ("import gf_core.native as n, pathlib\n"
            f"n.CSRC = pathlib.Path({str(src)!r})\n"
            "n.load()\n")
    env = dict(os.environ, GF_EXT_DIR=str(tmp_path / "ext"), GF_REQUIRE_NATIVE="1", GF_NO_CUDA="1")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode != 0
    assert "error: expected primary-expression" in r.stderr and "render_cpu.cpp" in r.stderr


def test_extension_cache_folder_is_per_source_checkout(tmp_path, monkeypatch):
    """Two checkouts sharing GF_EXT_DIR get a build folder each (ninja's build file names the
    sources by path: one shared folder would be rebuilt by each checkout in turn); the same
    checkout gets the same folder again."""
    import shutil

    from gf_core import native as ext

    monkeypatch.setenv("GF_EXT_DIR", str(tmp_path / "ext"))
    a = ext._build_dir(False, None)
    assert ext._build_dir(False, None) == a
    copy = tmp_path / "other" / "csrc"
    shutil.copytree(ext.CSRC, copy)
    monkeypatch.setattr(ext, "CSRC", copy)
    b = ext._build_dir(False, None)
    assert b != a and b.parent == a.parent
