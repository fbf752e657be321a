"""How a reconstruction moves between its training frames, for BENCHMARKS.md: the decoded
positions half-way between consecutive frames against the chord of the two frames' positions
(in the trainer's particle spacings), and the analytic speed |dp/dt| against the frames'
finite differences. A decoder whose time encoding has more frequencies than the frames sample
(``decoder.n_freqs``) fits the frames and strays between them.

    python scripts/subframe_motion.py RUN/recon.h5 [RUN2/recon.h5 ...]

The training frames' times are the decoder residuals' knots (a recon.h5 without residuals is refused).
"""
import sys

import numpy as np
import torch

from gf_core.formats.hdf5 import read_recon
from gf_core.recon.model import FluidModel

for path in sys.argv[1:]:
    r = read_recon(path)
    m = FluidModel.from_recon(r)
    sp = float(r.config["spacing"])
    if r.decoder is None or r.decoder.residual_knots is None:
        sys.exit(f"{path}: no decoder residuals, so no record of the training frames' times")
    ts = m.time_map.t_min + np.asarray(r.decoder.residual_knots, np.float64) * m.time_map.duration  # the frames
    with torch.no_grad():
        P = m.positions(ts).numpy()
        M = m.positions(0.5 * (ts[:-1] + ts[1:])).numpy()
        V = m.velocities(ts[::4]).numpy()
    off = np.linalg.norm(M - 0.5 * (P[:-1] + P[1:]), axis=-1) / sp
    fd = np.linalg.norm((P[1:] - P[:-1]) / np.diff(ts)[:, None, None], axis=-1)
    sv = np.linalg.norm(V, axis=-1)
    print(f"{path}: {len(ts)} frames; mid-frame distance from the chord mean {off.mean():.3f}, 99th percentile "
          f"{np.quantile(off, 0.99):.2f} spacings; analytic speed median {np.median(sv):.2f} m/s (99th percentile "
          f"{np.quantile(sv, 0.99):.1f}), frame differences median {np.median(fd):.2f} m/s")
