"""Diagnostic: how much of a reconstruction's error at one frame is its pose, how much its appearance?

Decodes RECON at time T, then optimises that frame's particles alone against the training views
(L1 + D-SSIM over random backgrounds, Adam at the trainer's phase-1 rates), freeing only the named
parameter groups, and prints training and held-out PSNR as it goes. Used for BENCHMARKS.md
("2026-11-27 (CPU benchmark bounds)"); not part of the toolkit's API.

    python scripts/refit_frame.py RUN/recon.h5 DATASET 0.6 means,log_scales,quats 400
    groups: means, log_scales, quats, opacity, sh  (or "all")

With GROUPS = "trainer" it runs the trainer's own phase-3 step instead (every loss term at its
final weight, the trainer's rates, residuals included), every draw at that frame, on the water
preset changed by any section.key=value arguments after ITERS (which term holds a frame back?):

    python scripts/refit_frame.py RUN/recon.h5 DATASET 0.6 trainer 400 train.times_per_step=1 loss.aniso=0
"""

import sys

import numpy as np
import torch

from gf_core.data import load_dataset
from gf_core.formats.hdf5 import read_recon
from gf_core.recon.model import FluidModel
from gf_core.recon.config import make_config
from gf_core.recon.terms.image import d_ssim, l1, psnr as image_psnr
from gf_core.recon.views import composite, load_views
from gf_core.render import render


def trainer_steps(recon, dataset, when, iters, overrides):
    """The trainer's phase-3 step at one frame, from RECON's particles and decoder."""
    import tempfile
    import tomllib
    from pathlib import Path

    from gf_core.recon.schedule import Plateau
    from gf_core.recon.trainer import Trainer

    over: dict = {}
    for a in overrides:
        key, value = a.split("=", 1)
        sec, key = key.split(".")
        over.setdefault(sec, {})[key] = tomllib.loads(f"x = {value}")["x"]
    r = read_recon(recon)
    cfg = make_config("water", overrides=over)
    tr = Trainer(cfg, load_dataset(dataset), test_ds=load_dataset(dataset, split="test"),
                 out=Path(tempfile.mkdtemp()), log=lambda *_: None)
    tr.initialise()
    tr.model = FluidModel.from_recon(r)
    tr.ctx.spacing, tr.ctx.h = float(r.config.get("spacing", tr.ctx.spacing)), float(r.config.get("h", tr.ctx.h))
    tr._make_optimizer()
    tr.phase, tr.plateau = 3, Plateau(10 ** 9, 0.0)
    t = float(tr.views.unique_times[np.argmin(np.abs(tr.views.unique_times - when))])
    tr.sampler.times = lambda phase, window: [t] * cfg.train.times_per_step

    def psnr(imgs):
        with torch.no_grad():
            p = tr.model.at(t)
            return np.mean([image_psnr(render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"],
                                          imgs.cameras[i], imgs.background, sh_degree=tr.model.sh_degree).color,
                                   composite(imgs.images[i], imgs.alphas[i], imgs.background))
                            for i in imgs.at_time(t)])

    print(f"t = {t:.4f} s, the trainer's phase-3 step {' '.join(overrides)}; start: train {psnr(tr.views):.2f} dB, "
          f"held-out {psnr(tr.test):.2f} dB")
    for it in range(1, iters + 1):
        tr.step(1.0, 1.0)
        if it % max(iters // 4, 1) == 0:
            print(f"{it:5d} steps: train {psnr(tr.views):.2f} dB, held-out {psnr(tr.test):.2f} dB")


def main(recon, dataset, when, groups, iters):
    m = FluidModel.from_recon(read_recon(recon))
    train = load_views(load_dataset(dataset), "cpu")
    test = load_views(load_dataset(dataset, split="test"), "cpu")
    t = float(train.unique_times[np.argmin(np.abs(train.unique_times - when))])
    with torch.no_grad():
        p = m.at(t)
    P = {"means": p["means"], "log_scales": p["scales"].log(), "quats": p["quats"],
         "opacity": torch.logit(p["opacities"].clamp(1e-4, 1 - 1e-4)), "sh": p["sh"]}
    P = {k: v.clone().requires_grad_() for k, v in P.items()}
    lr = make_config("water").lr  # the preset's phase-1 rates
    rates = {"means": lr.means * m.bounds.extent, "log_scales": lr.log_scales, "quats": lr.quats,
             "opacity": lr.logit_opacity, "sh": lr.sh_dc}
    names = list(rates) if groups == "all" else groups.split(",")
    opt = torch.optim.Adam([{"params": [P[k]], "lr": rates[k]} for k in names])

    def draw(imgs, i, bg):
        return render(P["means"], P["log_scales"].exp(), P["quats"], torch.sigmoid(P["opacity"]), P["sh"],
                      imgs.cameras[i], bg, sh_degree=m.sh_degree).color

    def psnr(imgs):
        with torch.no_grad():
            return np.mean([image_psnr(draw(imgs, i, imgs.background), composite(imgs.images[i], imgs.alphas[i],
                                                                               imgs.background))
                            for i in imgs.at_time(t)])

    print(f"t = {t:.4f} s, free: {', '.join(names)}; start: train {psnr(train):.2f} dB, held-out {psnr(test):.2f} dB")
    rng = np.random.default_rng(0)
    views = train.at_time(t)
    for it in range(1, iters + 1):
        bg = torch.rand(train.images[0].shape[-1])
        loss = 0.0
        for i in rng.choice(views, min(2, len(views)), replace=False):
            target = composite(train.images[i], train.alphas[i], bg)
            out = draw(train, i, bg)
            loss = loss + 0.8 * l1(out, target) + 0.2 * d_ssim(out, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % max(iters // 4, 1) == 0:
            print(f"{it:5d} steps: train {psnr(train):.2f} dB, held-out {psnr(test):.2f} dB")


if __name__ == "__main__":
    if len(sys.argv) < 6 or (len(sys.argv) > 6 and sys.argv[4] != "trainer"):
        sys.exit(__doc__)
    if sys.argv[4] == "trainer":
        trainer_steps(sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[5]), sys.argv[6:])
    else:
        main(sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4], int(sys.argv[5]))
