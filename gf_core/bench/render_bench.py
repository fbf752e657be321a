"""``gf-cli bench render``: renderer backends x particle counts x resolutions.

The scene (documented so figures can be compared): N particles uniform in a 1 m cube seen from
3 m (fx = 0.9 W), Gaussian std 0.5 x the particle spacing (1 m / N^(1/3)) with 10% jitter,
random rotations, opacity uniform in [0.05, 0.5], SH degree 1, RGB, float32. Forward and
forward+backward (loss = sum of colour and alpha) are timed separately; the figure is the
median of ``repeats`` runs after one warm-up.
"""

from __future__ import annotations


import torch

from ..camera import Camera
from .. import native
from ..render import render
from .common import median_time


def bench_scene(n: int, width: int, height: int, *, seed: int = 0, device="cpu", dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    cam = Camera.look_at([0.0, -3.0, 0.4], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], fx=0.9 * width,
                         width=width, height=height)
    spacing = 1.0 / max(n, 1) ** (1.0 / 3.0)
    params = [(torch.rand(n, 3, generator=g) - 0.5),
              0.5 * spacing * torch.exp(0.1 * torch.randn(n, 3, generator=g)),
              torch.randn(n, 4, generator=g),
              0.05 + 0.45 * torch.rand(n, generator=g),
              0.2 * torch.randn(n, 4, 3, generator=g)]
    return cam, [p.to(device=device, dtype=dtype) for p in params]


def _run(backend, cam, params, backward: bool):
    ps = [p.detach().clone().requires_grad_(backward) for p in params]
    out = render(*ps, cam, backend=backend)
    if backward:
        (out.color.sum() + out.alpha.sum()).backward()
    return out, ps


def bench_render(backends, counts, resolutions, *, repeats: int = 5, device: str = "cpu",
                 reference_max_work: float = 1.2e10, log=print) -> list[dict]:
    """One record per (backend, particles, resolution): forward and fwd+bwd seconds, plus for
    configurations both backends ran, the other backends' max difference from the reference and
    their speed-up over it."""
    sync = torch.cuda.synchronize if device.startswith("cuda") else None
    if "native" in backends and not native.available():
        log(f"native backend unavailable ({native.unavailable_reason()}); skipping it")
        backends = [b for b in backends if b != "native"]
    records = []
    for n in counts:
        for res in resolutions:
            cam, params = bench_scene(n, res, res, device=device)
            results = {}
            for be in backends:
                work = n * res * res
                rec = {"backend": be, "particles": n, "resolution": res, "device": device}
                if be == "reference" and work > reference_max_work:
                    rec["skipped"] = f"work {work:.1e} > reference_max_work {reference_max_work:.1e}"
                    records.append(rec)
                    log(f"{be:>9} {n:>7} {res:>4}  skipped (too slow)")
                    continue
                rec["forward_s"] = median_time(lambda: _run(be, cam, params, False), repeats, sync=sync)
                rec["forward_backward_s"] = median_time(lambda: _run(be, cam, params, True), repeats,
                                                        sync=sync)
                out, ps = _run(be, cam, params, True)
                results[be] = (out, ps)
                rec["visible"] = int((out.radii > 0).sum())
                records.append(rec)
                log(f"{be:>9} {n:>7} {res:>4}  fwd {rec['forward_s']:.4f} s  fwd+bwd "
                    f"{rec['forward_backward_s']:.4f} s")
            if len(results) > 1:
                base_name = "reference" if "reference" in results else next(iter(results))
                base_out, base_ps = results[base_name]
                for be, (out, ps) in results.items():
                    if be == base_name:
                        continue
                    rec = next(r for r in records if r["backend"] == be and r["particles"] == n
                               and r["resolution"] == res)
                    rec["compared_to"] = base_name
                    rec["max_abs_diff_color"] = float((out.color - base_out.color).abs().max())
                    rel = 0.0
                    for p, q in zip(ps, base_ps):
                        rel = max(rel, float((p.grad - q.grad).abs().max() / q.grad.abs().max().clamp_min(1e-30)))
                    rec["max_rel_diff_grads"] = rel
                    rec["speedup_fwd_bwd"] = next(r for r in records if r["backend"] == base_name and
                                                  r["particles"] == n and r["resolution"] == res
                                                  )["forward_backward_s"] / rec["forward_backward_s"]
    return records
