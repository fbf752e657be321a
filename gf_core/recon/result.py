"""What ``recon.h5`` says of a run beside its particles and decoder (its ``config`` attributes,
``docs/formats.md``): the configuration, the particle spacing and smoothing length, the fluid
volume the trained particles fill and the one the masks' hull held, where the scene box came
from, the dataset, the canonical time, the training frames' times and frame rate."""

from __future__ import annotations

import torch

from ..sph.density import particle_volume


def fluid_volume(model, times, h: float) -> float:
    """The fluid volume the trained particles fill at the training frames ``times`` (None for a
    static model): ``sph.density.particle_volume`` with the density loss's kernel and h. The
    particles' mass, and so every energy, and the spacing ``predict`` simulates at follow from it."""
    frames = []
    with torch.no_grad():
        for i in range(0, len(times), 8):  # eight frames per pass through the MLP
            frames += [p["means"] for p in model.at_many(times[i:i + 8])]
    return particle_volume(frames, h)


def result_config(tr) -> dict:
    """The ``config`` of the trainer ``tr``'s recon.h5."""
    meta = tr.dataset.meta
    times = [float(t) for t in tr.views.unique_times]
    return {"config": tr.cfg.to_dict(), "spacing": tr.ctx.spacing, "h": tr.ctx.h,
            "fluid_volume": fluid_volume(tr.model, [None] if tr.static else times, tr.ctx.h),
            "hull_volume": tr.volume, "scene_box_source": tr.box_source, "init": tr.init_source,
            "dataset_fingerprint": tr.fingerprint, "dataset": str(tr.dataset.root),
            "dataset_options": dict(meta.get("dataset_options", {})), "canonical_time_s": tr.t_canon,
            "time_source": meta.get("time_source", "seconds"), "channels": tr.views.channels,
            # the training frames' times: exports and the Blender extension sample these by default
            "frame_times_s": times, "fps": float(meta["fps"]) if meta.get("fps") else None}


__all__ = ["result_config", "fluid_volume"]
