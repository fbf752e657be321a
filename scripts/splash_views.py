"""Side-by-side views for BENCHMARKS.md: for times 0.2, 0.4, 0.6, 0.8 s, the first held-out view
(truth, reconstruction, 3x absolute error) then the first training view, one row per time.

    python scripts/splash_views.py RUN/recon.h5 DATASET OUT.png
"""
import sys, torch, numpy as np
from gf_core.formats.hdf5 import read_recon
from gf_core.recon.model import FluidModel
from gf_core.data import load_dataset
from gf_core.recon.trainer import load_images, composite
from gf_core.render import render
from PIL import Image
m = FluidModel.from_recon(read_recon(sys.argv[1]))
te = load_images(load_dataset(sys.argv[2], split="test"), "cpu")
tr = load_images(load_dataset(sys.argv[2]), "cpu")
rows = []
for T in (0.2, 0.4, 0.6, 0.8):
    t = float(te.unique_times[np.argmin(abs(te.unique_times - T))])
    with torch.no_grad():
        p = m.at(t)
        row = []
        for imgs, i in ((te, te.at_time(t)[0]), (tr, tr.at_time(t)[0])):
            o = render(p["means"], p["scales"], p["quats"], p["opacities"], p["sh"], imgs.cameras[i], imgs.background, sh_degree=1)
            g = composite(imgs.images[i], imgs.alphas[i], imgs.background)
            row += [g.numpy(), o.color.numpy(), np.abs(g.numpy() - o.color.numpy()) * 3]
    rows.append(np.concatenate(row, 1))
Image.fromarray((np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8)).save(sys.argv[3])
