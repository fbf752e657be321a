"""The numpy decoder (``gf_core.formats.decoder_np``, the Blender extension's) against the torch one."""

from __future__ import annotations

import numpy as np
import torch

from ..formats.decoder_np import NumpyDecoder
from ..recon.decoder import Decoder, DecoderConfig
from .common import median_time


def bench_decoder(n: int, repeats: int) -> dict:
    """Median milliseconds of one decode of ``n`` particles at one time (default dimensions:
    N_theta 64, 4 x 256), with weights scaled as after training (non-zero last layer)."""
    torch.manual_seed(0)
    dec = Decoder(n, DecoderConfig())
    with torch.no_grad():
        dec.features.normal_(0.0, 1.0)
        dec.layers[-1].weight.normal_(0.0, 0.01)
    nd = NumpyDecoder(dec.to_data())
    tau = 0.37
    t_np = median_time(lambda: nd(tau), repeats)
    t_npv = median_time(lambda: nd(tau, with_velocity=True), repeats)
    with torch.no_grad():
        t_t = median_time(lambda: dec(tau), repeats)
        ref = dec(tau)
    got = nd(tau)
    diff = max(float(np.abs(ref[k].numpy() - got[k]).max()) for k in ref)
    return {"particles": n, "numpy_ms": 1e3 * t_np, "numpy_velocity_ms": 1e3 * t_npv, "torch_ms": 1e3 * t_t,
            "ratio_numpy_torch": t_np / t_t, "max_abs_diff": diff, "repeats": repeats}
