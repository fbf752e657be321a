"""Diagnostic: how much of a reconstruction's error at one frame is its pose, how much its appearance?

Decodes RECON at time T, then optimises that frame's particles alone against the training views
(L1 + D-SSIM over random backgrounds, Adam at the trainer's phase-1 rates), freeing only the named
parameter groups, and prints training and held-out PSNR as it goes. Used for BENCHMARKS.md
("Eighth session"); not part of the toolkit's API.

    python scripts/refit_frame.py RUN/recon.h5 DATASET 0.6 means,log_scales,quats 400
    groups: means, log_scales, quats, opacity, sh  (or "all")
"""

import sys

import numpy as np
import torch

from gf_core import losses as L
from gf_core.data import load_dataset
from gf_core.io import read_recon
from gf_core.model import FluidModel
from gf_core.reconstruct import composite, load_images
from gf_core.render import render


def main(recon, dataset, when, groups, iters):
    m = FluidModel.from_recon(read_recon(recon))
    train = load_images(load_dataset(dataset), "cpu")
    test = load_images(load_dataset(dataset, split="test"), "cpu")
    t = float(train.unique_times[np.argmin(np.abs(train.unique_times - when))])
    with torch.no_grad():
        p = m.at(t)
    P = {"means": p["means"], "log_scales": p["scales"].log(), "quats": p["quats"],
         "opacity": torch.logit(p["opacities"].clamp(1e-4, 1 - 1e-4)), "sh": p["sh"]}
    P = {k: v.clone().requires_grad_() for k, v in P.items()}
    rates = {"means": 1.6e-4 * m.bounds.extent, "log_scales": 5e-3, "quats": 1e-3, "opacity": 5e-2, "sh": 2.5e-3}
    names = list(rates) if groups == "all" else groups.split(",")
    opt = torch.optim.Adam([{"params": [P[k]], "lr": rates[k]} for k in names])

    def draw(imgs, i, bg):
        return render(P["means"], P["log_scales"].exp(), P["quats"], torch.sigmoid(P["opacity"]), P["sh"],
                      imgs.cameras[i], bg, sh_degree=m.sh_degree).color

    def psnr(imgs):
        with torch.no_grad():
            return np.mean([L.psnr(draw(imgs, i, imgs.background), composite(imgs.images[i], imgs.alphas[i],
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
            loss = loss + 0.8 * L.l1(out, target) + 0.2 * L.d_ssim(out, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % max(iters // 4, 1) == 0:
            print(f"{it:5d} steps: train {psnr(train):.2f} dB, held-out {psnr(test):.2f} dB")


if __name__ == "__main__":
    if len(sys.argv) != 6:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4], int(sys.argv[5]))
