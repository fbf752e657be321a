"""Checkpoints of a training run (``RUN/checkpoint.pt``): written atomically every
``train.checkpoint_every`` iterations, at each phase end and on Ctrl-C; read back with every key,
type and per-particle tensor checked, so that a damaged file is one line naming the key."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..errors import GFError, InputError, ReconstructionError
from ..formats.hdf5 import atomic_path
from .config import from_dict
from .decoder import Decoder
from .model import FIXED, Bounds, FluidModel
from .schedule import Plateau

CHECKPOINT = "checkpoint.pt"
FORMAT = "gaussfluids.checkpoint"
PARAMS = ("means", "log_scales", "quats", "logit_opacity", "sh_dc", "sh_rest")
KEYS = {  # key -> the types it may hold (the schema of Trainer.checkpoint_state)
    "fingerprint": (str,), "config": (dict,), "bounds": (dict,), "params": (dict,), "mlp": (dict, type(None)),
    "optimizer": (dict,), "plateau": (dict,), "iteration": (int,), "phase": (int,), "phase_it": (int,),
    "elapsed": (int, float), "spacing": (int, float), "h": (int, float), "volume": (int, float),
    "box_source": (str,), "init_source": (str,), "rng_torch": (torch.Tensor,), "rng_numpy": (str,)}
OPTIONAL = {"phase_t0": (int, float), "total_bad_steps": (int,), "frame_err": (list,), "phase_ends": (list,),
            "guide": (dict,),
            "time_map": (list,)}


def check(st: dict, path) -> None:
    """The checkpoint's keys, types and per-particle tensors, one line naming the key otherwise."""
    def bad(what):
        raise InputError(path, f"damaged checkpoint: {what}; use --force to start afresh")

    for k, types in (*KEYS.items(), *OPTIONAL.items()):
        if k not in st:
            if k in OPTIONAL:
                continue
            bad(f"no {k!r}")
        v = st[k]
        if isinstance(v, bool) or not isinstance(v, types):
            bad(f"{k!r} is {type(v).__name__}, expected {' or '.join(t.__name__ for t in types)}")
        if isinstance(v, float) and not math.isfinite(v):
            bad(f"{k!r} is {v}")
    for k, nan_ok in (("frame_err", True), ("time_map", False)):  # frame_err: NaN = a frame not drawn yet
        if k in st and not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                               and (math.isfinite(x) or (nan_ok and math.isnan(x))) for x in st[k]):
            bad(f"{k!r} holds something other than {'numbers' if nan_ok else 'finite numbers'}")
    if not 1 <= st["phase"] <= 4 or st["iteration"] < 0 or st["phase_it"] < 0:
        bad(f"phase {st['phase']}, iteration {st['iteration']}, phase_it {st['phase_it']} out of range")
    params = st["params"]
    missing = [k for k in PARAMS if k not in params]
    if missing:
        bad(f"no per-particle {', '.join(missing)}")
    n = None
    for k, v in params.items():
        if not isinstance(v, torch.Tensor) or v.ndim < 1:
            bad(f"params.{k} is not a per-particle tensor")
        if n is None:
            n = v.shape[0]
        if v.shape[0] != n:
            bad(f"params.{k} has {v.shape[0]} rows, params.{next(iter(params))} {n}")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            bad(f"params.{k} has non-finite values")
    if st["mlp"] is not None and not all(isinstance(v, torch.Tensor) for v in st["mlp"].values()):
        bad("mlp holds something other than tensors")


def capture(tr) -> dict:
    """The trainer ``tr``'s state: everything a resumed run needs to go on as the uninterrupted one."""
    m = tr.model
    return {"config": tr.cfg.to_dict(), "fingerprint": tr.fingerprint, "iteration": tr.iteration,
            "phase": tr.phase, "phase_it": tr.phase_it, "phase_t0": tr.phase_t0, "elapsed": tr.elapsed,
            "spacing": tr.ctx.spacing, "h": tr.ctx.h, "volume": tr.volume, "box_source": tr.box_source,
            "init_source": tr.init_source, "bounds": m.bounds.to_dict(),
            "time_map": [tr.time_map.t_min, tr.time_map.t_max],
            "params": {k: v.detach().cpu() for k, v in {**m.per_particle(), **m.per_particle_fixed()}.items()},
            "mlp": None if m.decoder is None else {k: v.cpu() for k, v in m.decoder.layers.state_dict().items()},
            "optimizer": tr.opt.state_dict(), "plateau": tr.plateau.state(),
            "rng_torch": tr.gen.get_state(), "rng_numpy": json.dumps(tr.ctx.rng.bit_generator.state),
            "total_bad_steps": tr.total_bad_steps, "frame_err": tr.sampler.frame_err.tolist(),
            "phase_ends": list(tr.phase_end_reasons),
            **({"guide": dict(tr.guide_report)} if tr.guide_report is not None else {})}


def restore(tr, st: dict, path: Path) -> None:
    """A checked state (``read``) back into the trainer ``tr``; refuses one made from other images
    or another configuration."""
    if st["fingerprint"] != tr.fingerprint:
        raise ReconstructionError(f"{path}: the checkpoint was made from other images than the dataset given "
                                  "(files, times or cameras differ); use --force to start afresh")
    saved, now = from_dict(st["config"]).to_dict(), tr.cfg.to_dict()
    if saved != now:
        diff = [f"{s}.{k}" for s, sec in now.items() for k, v in sec.items() if saved[s][k] != v]
        raise ReconstructionError(f"{path}: the checkpoint was made with another configuration "
                                  f"({', '.join(diff[:6])} differ); resume with the same options or use --force")
    P = {k: v.to(tr.device) for k, v in st["params"].items()}
    dec = None
    if st["mlp"] is not None:
        dec = Decoder(P["means"].shape[0], tr.decoder_cfg, knots=tr.knots(), channels=tr.views.channels,
                      device=tr.device)
        dec.layers.load_state_dict(st["mlp"])
        dec.features = torch.nn.Parameter(P["features"])
        for name in dec.residuals():
            dec.set_residual(name, P[name])
    tr.model = FluidModel(P["means"], P["log_scales"], P["quats"], P["logit_opacity"],
                            torch.cat([P["sh_dc"], P["sh_rest"]], 1), bounds=Bounds.from_dict(st["bounds"]),
                            time_map=tr.time_map, decoder=dec)
    for name in FIXED:
        if name in P:
            tr.model.set_per_particle(name, P[name])
    tr.ctx.spacing, tr.ctx.h, tr.volume = st["spacing"], st["h"], st["volume"]
    tr.box_source, tr.init_source = st["box_source"], st["init_source"]
    tr.ctx.box_source = tr.box_source
    tr._make_optimizer()
    tr.opt.load_state_dict(st["optimizer"])
    tr.iteration, tr.phase, tr.phase_it = st["iteration"], st["phase"], st["phase_it"]
    tr.elapsed, tr.phase_t0 = st["elapsed"], st.get("phase_t0", 0.0)
    tr.total_bad_steps = st.get("total_bad_steps", 0)
    tr.phase_end_reasons = list(st.get("phase_ends", []))
    tr.guide_report = st.get("guide")
    if "frame_err" in st:
        tr.sampler.frame_err = np.asarray(st["frame_err"], np.float64)
    tr.plateau = Plateau(tr.cfg.phases.plateau_window, tr.cfg.phases.plateau_tol)
    tr.plateau.load(st["plateau"])
    tr.gen.set_state(st["rng_torch"])
    tr.ctx.rng.bit_generator.state = json.loads(st["rng_numpy"])
    tr.strategy.reset(len(tr.model), tr.device)


def write(path: Path, state: dict) -> Path:
    with atomic_path(path) as tmp:
        torch.save({"format": FORMAT, "version": 1, **state}, tmp)
    return path


def read(path: Path) -> dict:
    """The checked state of the checkpoint at ``path`` (one line for anything unreadable)."""
    try:
        st = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable checkpoint gets the same message
        raise InputError(path, f"cannot read the checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(st, dict) or st.get("format") != FORMAT:
        raise InputError(path, "not a GaussFluids checkpoint")
    check(st, path)
    return st


def applying(path: Path):
    """A context in which a checked state is applied: what the schema cannot see (an optimiser
    state or a layer of the wrong size) becomes one line too."""
    return _Applying(path)


class _Applying:
    def __init__(self, path):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, et, e, tb):
        if et is None or issubclass(et, GFError):
            return False
        if issubclass(et, (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError)):
            raise InputError(self.path, f"damaged checkpoint ({et.__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}); "
                                        "use --force to start afresh") from None
        return False


__all__ = ["CHECKPOINT", "FORMAT", "check", "read", "write", "applying", "capture", "restore"]
