"""Where the reconstructed particles are wrong, for BENCHMARKS.md: at each time given, the
reconstructed particles against the true ones of the dataset's gt_sim.h5 (x-z, y-z and x-y
projections; red: reconstructed particles more than 2 true spacings from any true one), and a line
per time: the mean distances both ways, the share of far particles and their median height
against the others', their opacities, and the most-crowded neighbourhoods (a pile).

    python scripts/particle_errors.py RUN/recon.h5 DATASET 0.2,0.4,0.7 OUT.png
"""
import sys

import matplotlib
import numpy as np
import torch
from scipy.spatial import cKDTree

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from gf_core.formats.hdf5 import read_recon, read_sim  # noqa: E402
from gf_core.eval.metrics import nearest_distance  # noqa: E402
from gf_core.recon.model import FluidModel  # noqa: E402

model = FluidModel.from_recon(read_recon(sys.argv[1]))
sim = read_sim(f"{sys.argv[2]}/gt_sim.h5")
times = [float(x) for x in sys.argv[3].split(",")]
sp = 2 * sim.particle_radius
fig, ax = plt.subplots(len(times), 3, figsize=(15, 4 * len(times)), squeeze=False)
for row, t in enumerate(times):
    f = int(np.argmin(abs(sim.times - t)))
    g = sim.positions[f]
    with torch.no_grad():
        st = model.at(t)
    p, op = st["means"].numpy(), st["opacities"].numpy().ravel()
    pt, gt = torch.as_tensor(p, dtype=torch.float64), torch.as_tensor(g, dtype=torch.float64)
    d = nearest_distance(pt, gt, sp).numpy() / sp  # as gf-cli evaluate measures them
    dg = nearest_distance(gt, pt, sp).numpy() / sp
    far = d > 2
    crowd = np.array([len(x) for x in cKDTree(p).query_ball_point(p, sp)]) - 1
    print(f"t = {t:g} s (true frame {f}): recon->true {d.mean():.3f}, true->recon {dg.mean():.3f} spacings; "
          f"{100 * far.mean():.1f}% of {len(p)} reconstructed particles > 2 spacings away (adding {(d * far).sum() / len(d):.3f} "
          f"to the mean); median height far {np.median(p[far, 2]) if far.any() else float('nan'):.3f} m, all "
          f"{np.median(p[:, 2]):.3f} m, true {np.median(g[:, 2]):.3f} m; median opacity far "
          f"{np.median(op[far]) if far.any() else float('nan'):.3f}, all {np.median(op):.3f}; reconstructed neighbours "
          f"within 1 spacing: median {np.median(crowd):.0f}, max {crowd.max()}")
    for c, (a, b) in enumerate([(0, 2), (1, 2), (0, 1)]):
        ax[row, c].scatter(g[:, a], g[:, b], s=2, c="orange", label="true")
        ax[row, c].scatter(p[~far, a], p[~far, b], s=1, c="blue", alpha=0.3, label="reconstructed")
        ax[row, c].scatter(p[far, a], p[far, b], s=3, c="red", label="reconstructed, > 2 spacings")
        ax[row, c].set_aspect("equal")
        ax[row, c].set_title(f"t = {t:g} s, {'xyz'[a]}-{'xyz'[b]}")
ax[0, 0].legend(loc="upper right", fontsize=7)
plt.tight_layout()
plt.savefig(sys.argv[4], dpi=60)
