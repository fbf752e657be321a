"""``gf-cli bench gpu``: the CUDA figures the GPU targets ask for, on one scene each.

1. Renderer forward+backward on the ``bench render`` scene (50k particles, 400x400 by default),
   median over repeats with a device synchronise around each, against gsplat's
   ``rasterization`` on the same particles and camera when gsplat is importable (same EWA
   low-pass 0.3, SH degree 1, tile 16), with the image difference between the two.
2. K-nearest (K = 64) within h over 50k particles plus the SPH density (Poly6) and its gradient
   (``losses.sph_density`` + backward): the density loss's whole neighbour step.
"""

from __future__ import annotations

import math

import torch

from ..recon.terms.density import density_uniformity
from ..sph.density import sph_density_knn
from ..sph.neighbors import knn
from ..render import render
from ..render.constants import TILE_SIZE, TILE_SIZE_CUDA
from .common import median_time
from .render_bench import bench_scene


def _sync():
    torch.cuda.synchronize()


def bench_renderer(n: int = 50000, res: int = 400, repeats: int = 50, tiles=(TILE_SIZE_CUDA, TILE_SIZE), log=print) -> dict:
    """Ours at each tile size in ``tiles`` (the first is the one compared with gsplat and profiled)."""
    cam, params = bench_scene(n, res, res, device="cuda")
    tile = tiles[0]

    def ours(tile=tile):
        ps = [p.detach().clone().requires_grad_(True) for p in params]
        out = render(*ps, cam, backend="native", tile_size=tile)
        (out.color.sum() + out.alpha.sum()).backward()
        return out

    rec = {"particles": n, "resolution": res, "device": torch.cuda.get_device_name(0), "tile": tile}
    for t in tiles:
        fwd = median_time(lambda: render(*params, cam, backend="native", tile_size=t), repeats, warmup=3, sync=_sync)
        both = median_time(lambda: ours(t), repeats, warmup=3, sync=_sync)
        rec[f"tile{t}"] = {"forward_s": fwd, "fwd_bwd_s": both}
        log(f"ours, tile {t}: forward {1e3 * fwd:.3f} ms, forward+backward {1e3 * both:.3f} ms")
    rec["ours_forward_s"] = rec[f"tile{tile}"]["forward_s"]
    rec["ours_fwd_bwd_s"] = rec[f"tile{tile}"]["fwd_bwd_s"]
    out = ours()
    rec["visible"] = int((out.radii > 0).sum())
    # where the time goes: kernel time against wall time (one profiled fwd+bwd after warm-up)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            ours()
        _sync()
    ka = prof.key_averages()
    kern = sorted([e for e in ka if getattr(e, "self_device_time_total", 0) > 0],
                  key=lambda e: -e.self_device_time_total)
    # (autograd Function entries carry their kernels' device time too: read the kernel lines)
    rec["device_time_us_per_iteration"] = {e.key[:60]: round(e.self_device_time_total / 5, 1) for e in kern[:14]}
    log("device time per fwd+bwd (us): " + ", ".join(f"{k}={v}" for k, v in rec["device_time_us_per_iteration"].items()))
    log(f"ours (tile {tile}): forward {1e3 * rec['ours_forward_s']:.3f} ms, forward+backward "
        f"{1e3 * rec['ours_fwd_bwd_s']:.3f} ms ({rec['visible']} visible)")
    try:
        import gsplat
        from gsplat import rasterization
    except ImportError as e:
        rec["gsplat"] = f"not importable ({e})"
        log(f"gsplat: {rec['gsplat']}")
        return rec
    rec["gsplat_version"] = getattr(gsplat, "__version__", "?")
    viewmat, _ = cam.to_torch(device="cuda", dtype=torch.float32)
    K = torch.tensor(cam.K, dtype=torch.float32, device="cuda")

    def theirs(backward=True):
        m, s, q, o, sh = [p.detach().clone().requires_grad_(backward) for p in params]
        img, alpha, _ = rasterization(m, q, s, o, sh, viewmat[None], K[None], res, res, near_plane=cam.near,
                                      sh_degree=1, eps2d=0.3, tile_size=16)
        if backward:
            (img.sum() + alpha.sum()).backward()
        return img, alpha

    rec["gsplat_forward_s"] = median_time(lambda: theirs(False), repeats, warmup=3, sync=_sync)
    rec["gsplat_fwd_bwd_s"] = median_time(theirs, repeats, warmup=3, sync=_sync)
    with torch.no_grad():
        img, alpha = theirs(False)
        mine = render(*params, cam, backend="native", tile_size=tile)
    rec["max_abs_diff_vs_gsplat"] = float((img[0] - mine.color).abs().max())
    rec["mean_abs_diff_vs_gsplat"] = float((img[0] - mine.color).abs().mean())
    rec["ratio_fwd_bwd_ours_over_gsplat"] = rec["ours_fwd_bwd_s"] / rec["gsplat_fwd_bwd_s"]
    log(f"gsplat {rec['gsplat_version']}: forward {1e3 * rec['gsplat_forward_s']:.3f} ms, forward+backward "
        f"{1e3 * rec['gsplat_fwd_bwd_s']:.3f} ms; ours/gsplat {rec['ratio_fwd_bwd_ours_over_gsplat']:.2f}; "
        f"image difference max {rec['max_abs_diff_vs_gsplat']:.3g}, mean {rec['mean_abs_diff_vs_gsplat']:.3g}")
    return rec


def bench_density(n: int = 50000, k: int = 64, repeats: int = 50, log=print) -> dict:
    """Particles jittered on a lattice of spacing s; h = 2.5 s (about 65 neighbours inside)."""
    side = math.ceil(n ** (1 / 3))
    g = torch.Generator().manual_seed(0)
    ax = torch.arange(side, dtype=torch.float32)
    P = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)[:n]
    P = (P + 0.2 * torch.randn(P.shape, generator=g)) * 0.01
    x = P.cuda()
    h = 2.5 * 0.01

    def step():
        xr = x.detach().clone().requires_grad_(True)
        idx, _ = knn(xr, k, h, backend="native", sorted=False)
        d = sph_density_knn(xr, idx, h)
        density_uniformity(d).backward()
        return idx

    rec = {"particles": n, "k": k, "h_in_spacings": 2.5}
    rec["knn_sorted_s"] = median_time(lambda: knn(x, k, h, backend="native"), repeats, warmup=3, sync=_sync)
    rec["knn_s"] = median_time(lambda: knn(x, k, h, backend="native", sorted=False), repeats, warmup=3, sync=_sync)
    rec["knn_density_grad_s"] = median_time(step, repeats, warmup=3, sync=_sync)
    idx = step()
    rec["mean_neighbours"] = float((idx >= 0).sum(1).float().mean())
    log(f"knn (K={k}) over {n} particles: {1e3 * rec['knn_s']:.3f} ms ({1e3 * rec['knn_sorted_s']:.3f} ms sorted); "
        f"with SPH density + gradient "
        f"{1e3 * rec['knn_density_grad_s']:.3f} ms ({rec['mean_neighbours']:.1f} neighbours on average)")
    return rec


__all__ = ["bench_renderer", "bench_density"]
