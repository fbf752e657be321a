"""The reconstruction model: canonical Gaussian particles A^0 (Sec. 3.1) plus, for a moving
fluid, the time-continuous decoder Phi (Sec. 3.2). Decodes the particles at any time, gives
their velocities, and converts to and from ``recon.h5`` (``io.ReconData``).

Raw parameters are what the optimiser sees (log-scales, logits, quaternions of any norm);
``at(t)`` returns what the renderer takes. Bounds keep every decoded particle finite and in
the scene: log-scales are clamped to [log s_min, log s_max] and positions to the domain box inset
by ``Bounds.inset`` (all derived from the scene at initialisation and stored with the model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..errors import InputError
from ..formats.decoder_np import centre_box
from ..formats.hdf5 import ReconData
from ..render.constants import SH_C0
from .decoder import COLOR_OUTPUT, OPACITY_OUTPUT, RESIDUAL_PREFIX, Decoder, DecoderConfig, TimeMap, apply_delta

PER_PARTICLE = ("means", "log_scales", "quats", "logit_opacity", "sh_dc", "sh_rest")
FIXED = ("guide_dp",)  # per-particle, not optimised (FluidModel.fixed)


@dataclass
class Bounds:
    lo: tuple          # domain box, metres
    hi: tuple
    log_scale_min: float
    log_scale_max: float
    inset: float = 0.0  # metres: particle centres stay this far inside every face of the box

    @property
    def extent(self) -> float:
        return float(np.linalg.norm(np.asarray(self.hi) - np.asarray(self.lo)))

    def centre_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of the particle centres: the box inset by ``inset`` on every face
        (``decoder_np.centre_box``, which the Blender extension's decoder uses too)."""
        return centre_box(self.lo, self.hi, self.inset)

    def to_dict(self) -> dict:
        return {"lo": list(self.lo), "hi": list(self.hi), "log_scale_min": self.log_scale_min,
                "log_scale_max": self.log_scale_max, "inset": self.inset}

    @classmethod
    def from_dict(cls, b: dict) -> "Bounds":
        """``to_dict``'s inverse; a recon.h5 written before ``inset`` existed has none (0)."""
        return cls(tuple(b["lo"]), tuple(b["hi"]), float(b["log_scale_min"]), float(b["log_scale_max"]),
                   float(b.get("inset", 0.0)))

    @classmethod
    def for_box(cls, lo, hi, spacing: float, inset: float = 0.0) -> "Bounds":
        """Scales between 1/50 of a particle spacing and a tenth of the box diagonal; centres
        ``inset`` metres inside the box."""
        ext = float(np.linalg.norm(np.asarray(hi, float) - np.asarray(lo, float)))
        return cls(tuple(map(float, lo)), tuple(map(float, hi)), math.log(spacing / 50.0), math.log(0.1 * ext),
                   float(inset))


class _WallClamp(torch.autograd.Function):
    """Positions clamped into [lo, hi] whose gradient still reaches a coordinate held at a wall
    when the descent step would move it back inside. A hard clamp's gradient is 0 there: a particle
    that the decoder pushed through the floor at some frame no longer feels the images at that frame
    along that axis and stays flattened on the floor however high the fluid in the images is."""

    @staticmethod
    def forward(ctx, x, lo, hi):
        ctx.save_for_backward(x, lo, hi)
        return torch.maximum(torch.minimum(x, hi), lo)

    @staticmethod
    def backward(ctx, g):
        x, lo, hi = ctx.saved_tensors
        # descent moves x by -g: below lo it must rise (g < 0), above hi fall (g > 0)
        keep = ((x >= lo) | (g < 0)) & ((x <= hi) | (g > 0))
        return torch.where(keep, g, torch.zeros_like(g)), None, None



class FluidModel(nn.Module):
    """Canonical particles as ``nn.Parameter``s (one per name in ``PER_PARTICLE``) + optional decoder."""

    def __init__(self, means, log_scales, quats, logit_opacity, sh, *, bounds: Bounds, time_map: TimeMap,
                 decoder: Decoder | None = None):
        super().__init__()
        self.means = nn.Parameter(means)
        self.log_scales = nn.Parameter(log_scales)
        self.quats = nn.Parameter(quats)
        self.logit_opacity = nn.Parameter(logit_opacity)
        self.sh_dc = nn.Parameter(sh[:, :1].contiguous())
        self.sh_rest = nn.Parameter(sh[:, 1:].contiguous())
        self.bounds = bounds
        self.time_map = time_map
        self.decoder = decoder
        clo, chi = bounds.centre_box()
        self._lo = torch.tensor(clo, dtype=means.dtype, device=means.device)
        self._hi = torch.tensor(chi, dtype=means.dtype, device=means.device)
        self.wall_gradient = "none"  # model.wall_gradient: "inward" lets the images pull a particle off a wall
        # per-particle tensors that training keeps aligned with the particles but does not optimise:
        # "guide_dp" (N, F, 3), the position residuals a simulator's continuation asks for (recon/guide.py)
        self.fixed: dict[str, torch.Tensor] = {}

    # ---- construction ----------------------------------------------------------------------------
    @classmethod
    def from_points(cls, points: torch.Tensor, *, radius: float, color, opacity: float, sh_degree: int,
                    channels: int, bounds: Bounds, time_map: TimeMap, decoder_cfg: DecoderConfig | None,
                    knots=None, seed: int = 0) -> "FluidModel":
        n = points.shape[0]
        if n < 1:
            raise InputError("reconstruct", "no particles to start from")
        dt, dev = points.dtype, points.device
        col = torch.as_tensor(np.asarray(color, np.float64)[:channels], dtype=dt, device=dev)
        sh = torch.zeros(n, (sh_degree + 1) ** 2, channels, dtype=dt, device=dev)
        sh[:, 0, :] = (col.clamp(0.02, 0.98) - 0.5) / SH_C0
        quats = torch.zeros(n, 4, dtype=dt, device=dev)
        quats[:, 0] = 1
        logit = math.log(opacity / (1 - opacity))
        dec = None
        if decoder_cfg is not None:
            torch.manual_seed(seed)
            dec = Decoder(n, decoder_cfg, knots=knots, channels=channels, dtype=dt, device=dev)
        return cls(points.clone(), torch.full((n, 3), math.log(radius), dtype=dt, device=dev), quats,
                   torch.full((n,), logit, dtype=dt, device=dev), sh, bounds=bounds, time_map=time_map,
                   decoder=dec)

    # ---- sizes -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(math.isqrt(1 + self.sh_rest.shape[1])) - 1

    @property
    def channels(self) -> int:
        return self.sh_dc.shape[2]

    @property
    def is_dynamic(self) -> bool:
        return self.decoder is not None

    def per_particle(self) -> dict[str, nn.Parameter]:
        out = {k: getattr(self, k) for k in PER_PARTICLE}
        if self.decoder is not None:
            out["features"] = self.decoder.features
            out.update(self.decoder.residuals())
        return out

    def per_particle_fixed(self) -> dict[str, torch.Tensor]:
        """The per-particle tensors that are not optimised (``fixed``); densify and prune cut and
        grow them with the parameters, checkpoints keep them, recon.h5 does not."""
        return dict(self.fixed)

    def set_per_particle(self, name: str, value: torch.Tensor) -> nn.Parameter:
        if name in FIXED:
            self.fixed[name] = value.detach().clone()
            return self.fixed[name]
        if name.startswith(RESIDUAL_PREFIX):
            return self.decoder.set_residual(name, value)
        if name == "features":
            return self.decoder.replace_features(value)
        p = nn.Parameter(value.detach().clone())
        setattr(self, name, p)
        return p

    # ---- decoding ----------------------------------------------------------------------------------
    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh_dc, self.sh_rest], 1)

    def _bounded(self, means, log_scales):
        if self.wall_gradient == "inward" and torch.is_grad_enabled() and means.requires_grad:
            means = _WallClamp.apply(means, self._lo, self._hi)
        else:
            means = torch.maximum(torch.minimum(means, self._hi), self._lo)
        log_scales = log_scales.clamp(self.bounds.log_scale_min, self.bounds.log_scale_max)
        return means, log_scales

    def at(self, t: float | None = None, *, with_velocity: bool = False, use_decoder: bool = True) -> dict:
        """Renderer inputs at time ``t`` (seconds; None or a static model: the canonical particles):
        means, scales, quats, opacities, sh; with ``with_velocity`` also velocities (m/s)."""
        return self.at_many([t], with_velocity=with_velocity, use_decoder=use_decoder)[0]

    def at_many(self, times, *, with_velocity: bool = False, use_decoder: bool = True,
                with_unclamped: bool = False) -> list[dict]:
        """``at`` for several times, decoded in one pass through the MLP; with ``with_unclamped``
        also the decoded positions before the box holds them (``unclamped``, for loss.container)."""
        raw = {"means": self.means, "log_scales": self.log_scales, "quats": self.quats}
        decode = self.decoder is not None and use_decoder and all(t is not None for t in times)
        delta = None
        if decode:
            delta = self.decoder.forward_many([self.time_map.tau(t) for t in times], with_velocity=with_velocity)
        opacities, sh = torch.sigmoid(self.logit_opacity), self.sh()  # the same at every time
        out = []
        for k in range(len(times)):
            r, vel, sh_k, op_k = raw, None, sh, opacities
            if delta is not None and COLOR_OUTPUT in delta:  # colour residuals: the base colour at this time
                sh_k = torch.cat([self.sh_dc + delta[COLOR_OUTPUT][k][:, None, :], self.sh_rest], 1)
            if delta is not None and OPACITY_OUTPUT in delta:  # opacity residuals: the opacity at this time
                op_k = torch.sigmoid(self.logit_opacity + delta[OPACITY_OUTPUT][k][:, 0])
            if delta is not None:
                r = apply_delta(raw, {name: v[k] for name, v in delta.items()})
                if with_velocity:
                    vel = delta["vp"][k] / max(self.time_map.duration, 1e-12)
            means, log_scales = self._bounded(r["means"], r["log_scales"])
            p = {"means": means, "scales": torch.exp(log_scales), "quats": r["quats"],
                 "opacities": op_k, "sh": sh_k}
            if delta is not None and with_unclamped:
                p["unclamped"] = r["means"]
            if with_velocity:  # the clamp's derivative: a coordinate held at a wall does not move
                p["velocities"] = torch.zeros_like(means) if vel is None else torch.where(means == r["means"], vel, 0.0)
            out.append(p)
        return out

    @torch.no_grad()
    def positions(self, times) -> torch.Tensor:
        """(T, N, 3) particle positions at each time in ``times`` (seconds)."""
        return torch.stack([self.at(float(t))["means"] for t in np.atleast_1d(times)])

    def velocities(self, times) -> torch.Tensor:
        """(T, N, 3) velocities dp/dt in m/s (analytic, forward-mode through Phi)."""
        with torch.no_grad():
            return torch.stack([self.at(float(t), with_velocity=True)["velocities"] for t in np.atleast_1d(times)])

    # ---- keeping parameters sane -------------------------------------------------------------------
    @torch.no_grad()
    def project_(self) -> None:
        """After an optimiser step: unit quaternions, scales and positions inside their bounds."""
        n = self.quats.norm(dim=-1, keepdim=True)
        bad = ~(n > 1e-8)  # where-arithmetic, not boolean indexing: no device synchronisation
        ident = torch.zeros_like(self.quats)
        ident[:, 0] = 1
        self.quats.copy_(torch.where(bad, ident, self.quats / torch.where(bad, torch.ones_like(n), n)))
        self.log_scales.clamp_(self.bounds.log_scale_min, self.bounds.log_scale_max)
        self.means.copy_(torch.maximum(torch.minimum(self.means, self._hi), self._lo))
        self.logit_opacity.clamp_(-12.0, 12.0)

    # ---- recon.h5 ------------------------------------------------------------------------------------
    def to_recon(self, *, config: dict | None = None, metrics: dict | None = None) -> ReconData:
        cfg = dict(config or {})
        cfg["bounds"] = self.bounds.to_dict()
        cfg["time_policy"] = self.time_map.policy
        det = {k: v.detach().cpu().numpy() for k, v in self.per_particle().items()}
        return ReconData(means=det["means"], log_scales=det["log_scales"], quats=det["quats"],
                         logit_opacity=det["logit_opacity"],
                         sh=np.concatenate([det["sh_dc"], det["sh_rest"]], 1),
                         time_min=self.time_map.t_min,
                         time_max=self.time_map.t_max if self.time_map.t_max > self.time_map.t_min
                         else self.time_map.t_min + 1.0,
                         decoder=None if self.decoder is None else self.decoder.to_data(),
                         config=cfg, metrics=dict(metrics or {}))

    @classmethod
    def from_recon(cls, r: ReconData, *, device="cpu", dtype=torch.float32, time_policy: str | None = None) -> "FluidModel":
        def t(a):
            return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)

        b = r.config.get("bounds")
        if b:
            bounds = Bounds.from_dict(b)
        else:  # a recon.h5 written by another tool: bounds from the particles themselves
            lo, hi = r.means.min(0), r.means.max(0)
            pad = 0.1 * (hi - lo + 1e-3)
            bounds = Bounds(tuple((lo - pad).tolist()), tuple((hi + pad).tolist()),
                            float(r.log_scales.min()) - 5, float(r.log_scales.max()) + 5)
        static = r.decoder is None
        tm = TimeMap(r.time_min, r.time_min if static else r.time_max,
                     time_policy or r.config.get("time_policy", "clamp"))
        dec = None if static else Decoder.from_data(r.decoder, dtype=dtype, device=device)
        return cls(t(r.means), t(r.log_scales), t(r.quats), t(r.logit_opacity), t(r.sh), bounds=bounds,
                   time_map=tm, decoder=dec)


__all__ = ["FluidModel", "Bounds", "PER_PARTICLE"]
