"""The CUDA backend against the CPU backend (marker ``gpu``: run with ``pytest -m gpu`` on a
machine with a CUDA GPU; ``scripts/gpu_check.sh`` does). Outputs and every gradient must agree
to 1e-4 relative (norm) in float32 and to 1e-9 in float64."""

import math

import pytest
import torch

from gf_core.camera import Camera
from gf_core.errors import InputError
from gf_core.sph.neighbors import knn
from gf_core import native
from gf_core.render import render

pytestmark = pytest.mark.gpu


@pytest.fixture(scope="module", autouse=True)
def cuda_build():
    if not torch.cuda.is_available():
        pytest.fail("the gpu tests need a CUDA device (run them with -m gpu on a GPU machine)")
    assert native.available(), native.unavailable_reason()
    assert native.has_cuda(), "the native extension was built without CUDA"


def cam(W=64, H=48, fx=60.0):
    return Camera.look_at([0.3, -3.0, 0.5], [0, 0, 0], [0, 0, 1], fx=fx, width=W, height=H)


def scene(n, *, dtype, degree=1, channels=3, seed=0, spread=1.2, log_scale=-2.6):
    g = torch.Generator().manual_seed(seed)
    return [(torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * spread,
            torch.exp(torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3 + log_scale),
            torch.randn(n, 4, generator=g, dtype=torch.float64),
            torch.rand(n, generator=g, dtype=torch.float64) * 0.7 + 0.1,
            torch.randn(n, (degree + 1) ** 2, channels, generator=g, dtype=torch.float64) * 0.3]


def run(params, camera, device, dtype, *, depth=True, seed=3, tile=None):
    ps = [p.to(device=device, dtype=dtype).detach().clone().requires_grad_(True) for p in params]
    ch = params[4].shape[2]
    out = render(*ps, camera, background=torch.full((ch,), 0.25, dtype=dtype, device=device), backend="native",
                 return_depth=depth, tile_size=tile)
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(out.color.shape, generator=g, dtype=torch.float32).to(device=device, dtype=dtype)
    loss = (out.color * w).sum() + (out.alpha ** 2).sum() + (0.1 * out.depth.sum() if depth else 0)
    loss.backward()
    return out, ps


def rel_norm(a, b):
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@pytest.mark.parametrize("n, W, H, degree, channels", [
    (60, 33, 17, 0, 1), (2000, 97, 80, 1, 3), (20000, 256, 256, 2, 3), (5000, 128, 128, 3, 1),
    (50000, 400, 400, 1, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu(n, W, H, degree, channels, dtype):
    params = scene(n, dtype=dtype, degree=degree, channels=channels, seed=n % 7)
    c = cam(W, H, fx=0.9 * W)
    o_cpu, p_cpu = run(params, c, "cpu", dtype)
    o_gpu, p_gpu = run(params, c, "cuda", dtype)
    assert o_gpu.backend == "native"
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert torch.equal(o_cpu.radii, o_gpu.radii.cpu())
    for name in ("color", "alpha", "depth"):
        assert rel_norm(getattr(o_gpu, name), getattr(o_cpu, name)) < tol, name
    for k, (a, b) in enumerate(zip(p_gpu, p_cpu)):
        assert rel_norm(a.grad, b.grad) < tol, ("means", "scales", "quats", "opacities", "sh")[k]
    assert rel_norm(o_gpu.means2d.grad, o_cpu.means2d.grad) < tol


@pytest.mark.parametrize("n, W, H", [(2000, 97, 80), (50000, 400, 400)])
def test_cuda_tile16_matches_cpu(n, W, H):
    """The image does not depend on the tile size: CUDA with 16x16 tiles (8x8 is its default) against
    the CPU's 16x16."""
    dtype = torch.float32
    params = scene(n, dtype=dtype, seed=n % 5)
    c = cam(W, H, fx=0.9 * W)
    o_cpu, p_cpu = run(params, c, "cpu", dtype)
    o_gpu, p_gpu = run(params, c, "cuda", dtype, tile=16)
    for name in ("color", "alpha", "depth"):
        assert rel_norm(getattr(o_gpu, name), getattr(o_cpu, name)) < 1e-4, name
    for k, (a, b) in enumerate(zip(p_gpu, p_cpu)):
        assert rel_norm(a.grad, b.grad) < 1e-4, ("means", "scales", "quats", "opacities", "sh")[k]


def test_cuda_robustness():
    """Behind the camera, at the camera, degenerate and huge Gaussians, an empty image: finite,
    and equal to the CPU backend."""
    dt = torch.float32
    c = cam(40, 30, fx=40.0)
    centre = torch.tensor(c.center, dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.1], centre.tolist(), (centre + torch.tensor([0, -1.0, 0])).tolist(),
                          [0.0, 0.0, 0.05], [0.2, 0.1, 0.0]], dtype=torch.float64)
    scales = torch.tensor([[0.1] * 3, [1e-9] * 3, [0.1] * 3, [0.1] * 3, [50.0, 1e-6, 1e-6], [0.0, 0.0, 0.0]],
                          dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0.3, 0.2, 0.1, 0.9],
                          [1, 0, 0, 0]], dtype=torch.float64)
    opac = torch.tensor([0.5, 0.9, 0.5, 0.5, 0.9, 0.5], dtype=torch.float64)
    sh = torch.zeros(6, 4, 3, dtype=torch.float64)
    params = [means, scales, quats, opac, sh]
    o_cpu, p_cpu = run(params, c, "cpu", dt)
    o_gpu, p_gpu = run(params, c, "cuda", dt)
    assert torch.isfinite(o_gpu.color).all() and torch.isfinite(o_gpu.alpha).all()
    assert rel_norm(o_gpu.color, o_cpu.color) < 1e-4
    for a, b in zip(p_gpu, p_cpu):
        assert torch.isfinite(a.grad).all()
        assert rel_norm(a.grad, b.grad) < 1e-4 or float(b.grad.abs().max()) == 0.0
    # nothing in view: background everywhere, zero gradients
    far = [p.clone() for p in params]
    far[0] = far[0] - torch.tensor([0.0, 10.0, 0.0], dtype=torch.float64)  # behind the camera
    o, ps = run(far, c, "cuda", dt, depth=False)
    assert torch.allclose(o.color, torch.full_like(o.color, 0.25)) and float(o.alpha.abs().max()) == 0.0


def test_cuda_dtype_errors_name_the_tensor():
    p = scene(10, dtype=torch.float32)
    ps = [x.float().cuda() for x in p]
    ps[1] = ps[1].double()
    with pytest.raises(InputError, match="scales is torch.float64 but means is torch.float32"):
        render(*ps, cam())
    ps = [x.cuda().half() for x in p]
    with pytest.raises(InputError, match="means is torch.float16"):
        render(*ps, cam())


@pytest.mark.parametrize("n, k", [(1, 8), (1000, 16), (20000, 64), (50000, 64)])
def test_cuda_knn_matches_cpu(n, k):
    g = torch.Generator().manual_seed(n)
    x = torch.rand(n, 3, generator=g) * (n / 1000.0) ** (1 / 3)
    h = 0.25
    i_cpu, d_cpu = knn(x, k, h, backend="native")
    i_gpu, d_gpu = knn(x.cuda(), k, h, backend="native")
    assert torch.equal(i_cpu, i_gpu.cpu())
    fin = torch.isfinite(d_cpu)
    assert torch.equal(fin, torch.isfinite(d_gpu.cpu()))
    assert torch.allclose(d_cpu[fin], d_gpu.cpu()[fin], rtol=1e-5, atol=1e-7)


def test_reconstruct_runs_on_cuda(tmp_path):
    from gf_core.data import load_dataset
    from gf_core.eval.evaluate import evaluate
    from gf_core.recon.config import make_config
    from gf_core.recon.trainer import reconstruct
    from gf_core.synthetic import falling_blob, splat_dataset

    root = splat_dataset(tmp_path / "blob", falling_blob())
    cfg = make_config("water", overrides={"phases": {"iterations": 600, "limit_factor": 1.0}, "model": {"init_particles": 500,
                                                                                    "max_particles": 1000}})
    m = reconstruct(load_dataset(root), tmp_path / "run", cfg, test_dataset=load_dataset(root, split="test"),
                    device="cuda", log=lambda s: None)
    assert m["bad_steps"] == 0 and math.isfinite(m["test_psnr"])
    r = evaluate(tmp_path / "run", dataset=load_dataset(root), device="cuda", log=lambda s: None)
    assert r["train"]["psnr_mean"] > 28
    assert r["particles_vs_gt"]["gt_to_recon_max_frame"] < 1.0

