"""Time-continuous motion of Gaussian particles (paper Sec. 3.2, Eq. 4).

Each particle carries a transform feature theta (N_theta values); one MLP Phi shared by every
particle maps [theta, gamma(tau)] to the pose change Delta A = (Delta p, Delta s, Delta r):

    A^t = A^0 + Delta A^t,    Delta A^t = (tau - tau0) * Phi(theta, gamma(tau))          (Eq. 4)

tau is the time normalised to [0, 1] over the training clip, gamma the NeRF frequency encoding
(Rahaman et al. 2019 / Mildenhall et al. 2020): gamma(tau) = [tau, sin(2^k pi tau), cos(2^k pi tau)]
for k = 0..L-1. The factor (tau - tau0) makes the decoded particles equal the canonical ones at
the canonical time tau0 exactly, whatever the weights; the last layer starts at zero, so every
time decodes to the canonical particles when training starts.

Velocities dp/dt come from forward-mode differentiation of the same MLP along tau (one extra
pass with the ReLU masks of the forward pass), not from finite differences:
    d(Delta p)/dtau = Phi_p + (tau - tau0) dPhi_p/dtau,   dp/dt = d(Delta p)/dtau / (t_max - t_min).

Optional residuals (``DecoderConfig.residuals``, not in the paper): per-particle corrections R_i
at knots (the training frames' tau), interpolated between them and constant outside,

    Delta A^t = (tau - tau0) * Phi(theta, gamma(tau)) + R(tau) - R(tau0),

still exactly A^0 at tau0. With ``DecoderConfig.canonical_residual`` the canonical frame has a
residual of its own and none is subtracted,

    Delta A^t = (tau - tau0) * Phi(theta, gamma(tau)) + R(tau),

the same family of motions reparametrised: the canonical frame is then A^0 + R(tau0), fitted by
its own per-particle corrections like every other frame instead of by the canonical particles
that every frame shares. ``DecoderConfig.residual_interpolation = "hermite"`` joins the knots
with cubic Hermite segments whose tangents are the three-point derivatives at the knots
(``hermite_coefficients``): positions and velocities are continuous across the training frames,
and a particle in free fall (positions quadratic in time) gets its exact velocity away from the
clip's first and last segment (chords there). "linear" (the
files written before it) joins them with straight pieces, whose velocity jumps at every frame. At
a knot both give R_j exactly, so a step at the training frames trains the same values either way. All
T times of a training step go through the MLP as one batch (``forward_many``).

Optional appearance residuals (not in the paper, they need the pose residuals' knots): the same
R(tau) - R(tau0) (or R(tau) with ``canonical_residual``) on each particle's degree-0 SH coefficient (its base colour;
``DecoderConfig.color_residuals``, output ``dc`` (N, channels)) and on its logit opacity
(``DecoderConfig.opacity_residuals``, output ``do`` (N, 1)). The particles' geometry is
unchanged; what changes in time is only how a particle looks (a rendered water surface glints
differently in every frame, which particles of one colour and opacity cannot show).

The numpy twin in ``gf_core/decoder_np.py`` (used by the Blender extension, which has no torch)
evaluates the same function; a test holds the two equal.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

# TimeMap (seconds <-> tau) and the output layout are shared with the numpy twin, which needs no torch
from ..formats.decoder_np import (OUTPUTS, RESIDUAL_INTERPOLATIONS, TIME_INTERPOLATIONS, TimeMap, canonical_residual,
                         residual_interpolation,
                         tangent_table, time_interpolation)
from ..errors import InputError

RESIDUAL_PREFIX = "residual_"  # parameter names: residual_dp, residual_ds, residual_dr (, residual_dc, residual_do)
COLOR_OUTPUT = "dc"            # the colour residuals' output: change of the degree-0 SH coefficient (N, channels)
OPACITY_OUTPUT = "do"          # the opacity residuals' output: change of the logit opacity (N, 1)


@dataclass
class DecoderConfig:
    feature_dim: int = 64        # N_theta (paper Sec. 4.1.2)
    hidden_layers: int = 4       # paper: 4 hidden layers
    hidden_width: int = 256      # paper: 256 neurons per layer
    n_freqs: int = 6             # L of gamma(tau)
    include_input: bool = True   # tau itself in gamma(tau)
    canonical_time: float = 0.0  # tau0 in [0, 1]
    residuals: bool = False      # per-particle pose corrections at the training frames (not in the paper)
    color_residuals: bool = False  # per-particle base-colour corrections at the same knots (not in the paper)
    opacity_residuals: bool = False  # per-particle logit-opacity corrections at the same knots (not in the paper)
    canonical_residual: bool = False  # the canonical frame's knot has residuals too: Delta A = (tau - tau0) Phi + R(tau)
    residual_interpolation: str = "hermite"  # between the knots: "hermite" (C1) or "linear"
    time_interpolation: str = "decoder"  # between the knots: "decoder" (Phi at tau, Eq. 4) or "knots" (Phi at the
                                         # knots joined by the residuals' Hermite segments; needs residuals)

    def validate(self) -> "DecoderConfig":
        for k in ("feature_dim", "hidden_layers", "hidden_width"):
            if int(getattr(self, k)) < 1:
                raise InputError("decoder config", f"{k} must be >= 1, got {getattr(self, k)}")
        if int(self.n_freqs) < 0:
            raise InputError("decoder config", f"n_freqs must be >= 0, got {self.n_freqs}")
        if not 0.0 <= float(self.canonical_time) <= 1.0:
            raise InputError("decoder config", f"canonical_time must be in [0, 1], got {self.canonical_time}")
        for k in ("color_residuals", "opacity_residuals", "canonical_residual"):
            if getattr(self, k) and not self.residuals:
                raise InputError("decoder config", f"{k} need residuals = true (they share its knots)")
        if self.residual_interpolation not in RESIDUAL_INTERPOLATIONS:
            raise InputError("decoder config", f"residual_interpolation must be one of "
                                               f"{', '.join(RESIDUAL_INTERPOLATIONS)}, got {self.residual_interpolation!r}")
        if self.time_interpolation not in TIME_INTERPOLATIONS:
            raise InputError("decoder config", f"time_interpolation must be one of {', '.join(TIME_INTERPOLATIONS)}, "
                                               f"got {self.time_interpolation!r}")
        if self.time_interpolation == "knots" and (not self.residuals or self.residual_interpolation != "hermite"):
            raise InputError("decoder config", "time_interpolation = 'knots' needs residuals = true and "
                                               "residual_interpolation = 'hermite' (it joins the same knots the same way)")
        if int(self.n_freqs) == 0 and not self.include_input:
            raise InputError("decoder config", "the time encoding is empty (n_freqs 0 and no include_input)")
        return self

    @property
    def encoding_dim(self) -> int:
        return (1 if self.include_input else 0) + 2 * int(self.n_freqs)


def encode_time(tau: torch.Tensor, n_freqs: int, include_input: bool = True) -> torch.Tensor:
    """gamma(tau) (..., D) and its derivative along tau (..., D)."""
    tau = tau[..., None]
    parts, dparts = [], []
    if include_input:
        parts.append(tau)
        dparts.append(torch.ones_like(tau))
    if n_freqs > 0:
        w = math.pi * (2.0 ** torch.arange(n_freqs, dtype=tau.dtype, device=tau.device))
        arg = tau * w
        parts += [torch.sin(arg), torch.cos(arg)]
        dparts += [torch.cos(arg) * w, -torch.sin(arg) * w]
    return torch.cat(parts, -1), torch.cat(dparts, -1)


def hermite_coefficients(knots: torch.Tensor, tangents: torch.Tensor, tau_t: torch.Tensor):
    """The cubic Hermite residual interpolation of ``gf_core.formats.decoder_np.hermite_coefficients`` (its
    docstring has the equations) for T times at once, with ``tangents`` = ``tangent_table(knots)``:
    (indices (T, 4) of knots j-1..j+2 clamped, value weights (T, 4), derivative weights (T, 4))."""
    k = knots
    f = k.numel()
    t = tau_t.detach()
    tc = t.clamp(k[0], k[-1])
    j = (torch.searchsorted(k, tc, right=True) - 1).clamp(0, f - 2)
    h1 = k[j + 1] - k[j]
    s = (tc - k[j]) / h1
    s2, s3 = s * s, s * s * s
    m = tangents[j]  # (T, 2, 4): m_j, m_{j+1}
    e1 = torch.zeros(t.shape[0], 4, dtype=k.dtype, device=k.device)
    e2 = e1.clone()
    e1[:, 1], e2[:, 2] = 1.0, 1.0

    def weights(h00, h10, h01, h11):
        return h00[:, None] * e1 + h01[:, None] * e2 + h1[:, None] * (h10[:, None] * m[:, 0] + h11[:, None] * m[:, 1])

    inside = ((t >= k[0]) & (t <= k[-1])).to(k.dtype)
    wv = weights(2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2)
    wd = weights(6 * s2 - 6 * s, 3 * s2 - 4 * s + 1, -6 * s2 + 6 * s, 3 * s2 - 2 * s) * (inside / h1)[:, None]
    idx = (j[:, None] + torch.arange(-1, 3, device=j.device)).clamp(0, f - 1)
    return idx, wv, wd


class Decoder(nn.Module):
    """Phi: per-particle features theta (N, N_theta) and the shared MLP.

    The first layer's weight is split into its theta part and its gamma part, so that the time
    encoding is multiplied once per time, not once per particle.
    """

    def __init__(self, num_particles: int, cfg: DecoderConfig | None = None, *, knots=None, channels: int = 3,
                 dtype=torch.float32, device=None):
        super().__init__()
        self.cfg = (cfg or DecoderConfig()).validate()
        c = self.cfg
        # residuals (cfg.residuals): R (N, F, k) per output at the F knots (the training frames' tau),
        # linear in tau between them: Delta A^t = (tau - tau0) Phi + R(tau) - R(tau0)
        self.register_buffer("knots", None, persistent=False)
        self.register_buffer("knot_free", None, persistent=False)
        if c.residuals:
            kn = torch.as_tensor(knots if knots is not None else [], dtype=torch.float64)
            if kn.ndim != 1 or kn.numel() < 2 or not bool((kn[1:] > kn[:-1]).all()):
                raise InputError("decoder config", "residuals need at least 2 increasing knots (the frames' tau)")
            self.knots = kn.to(dtype=dtype, device=device)
            self._knots_np = kn.numpy().copy()
            # the Hermite tangents' weights per segment, fixed with the knots (residual_interpolation)
            self.register_buffer("tangents", torch.as_tensor(tangent_table(kn.numpy()), dtype=dtype, device=device),
                                 persistent=False)
            # R is 0 at the canonical frame's knot (R(tau) - R(tau0): it would only shift every other
            # frame), unless the canonical frame has residuals of its own (canonical_residual)
            self.knot_free = torch.ones_like(self.knots) if c.canonical_residual else \
                ((self.knots - c.canonical_time).abs() > 1e-6).to(dtype)
            widths = dict(OUTPUTS, **({COLOR_OUTPUT: int(channels)} if c.color_residuals else {}),
                          **({OPACITY_OUTPUT: 1} if c.opacity_residuals else {}))
            for name, width in widths.items():
                setattr(self, RESIDUAL_PREFIX + name,
                        nn.Parameter(torch.zeros(num_particles, kn.numel(), width, dtype=dtype, device=device)))
        # theta starts at zero (paper: "both are initialised to zero"); the hidden layers get the
        # default init so that gradients reach theta once the last layer moves away from zero.
        self.features = nn.Parameter(torch.zeros(num_particles, c.feature_dim, dtype=dtype, device=device))
        widths = [c.feature_dim + c.encoding_dim] + [c.hidden_width] * c.hidden_layers
        layers = [nn.Linear(a, b, dtype=dtype, device=device) for a, b in zip(widths[:-1], widths[1:])]
        last = nn.Linear(widths[-1], sum(OUTPUTS.values()), dtype=dtype, device=device)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.layers = nn.ModuleList(layers + [last])
        self._frozen = None  # freeze(): {tau: (tau - tau0) Phi (N, outputs)} while frozen
        # a lower precision (torch.bfloat16) for the hidden layers' matrix products in passes that
        # record gradients (training steps); None = the parameters' dtype. Passes without gradients
        # (the frozen decoder's cache, evaluation, export) and the last layer stay in full precision,
        # so the decoder that is saved and evaluated is the float32 one. Set by the trainer
        # (train.mlp_precision), not saved.
        self.mlp_dtype = None

    @property
    def num_particles(self) -> int:
        return self.features.shape[0]

    def mlp_parameters(self):
        return list(self.layers.parameters())

    def residuals(self) -> dict:
        """{'residual_dp': (N, F, 3), ..., 'residual_dc': (N, F, C) with colour residuals,
        'residual_do': (N, F, 1) with opacity residuals} (empty without residuals)."""
        if self.knots is None:
            return {}
        names = list(OUTPUTS) + self.appearance_outputs()
        return {RESIDUAL_PREFIX + n: getattr(self, RESIDUAL_PREFIX + n) for n in names}

    def appearance_outputs(self) -> list:
        """The appearance residuals' output names ('dc', 'do') this decoder has."""
        c = self.cfg
        return [n for n, on in ((COLOR_OUTPUT, c.color_residuals), (OPACITY_OUTPUT, c.opacity_residuals))
                if on and self.knots is not None]

    def residual_at(self, tau_t: torch.Tensor, name: str, coef=None):
        """R(tau) (T, N, k) and dR/dtau (T, N, k) of output ``name``: between the knots as
        ``cfg.residual_interpolation`` says, constant outside them. ``coef``: the Hermite
        coefficients of ``tau_t`` when the caller has them (one evaluation for all outputs)."""
        k = self.knots
        r, free = getattr(self, RESIDUAL_PREFIX + name), self.knot_free
        if self.cfg.residual_interpolation == "hermite":
            idx, wv, wd = coef if coef is not None else hermite_coefficients(k, self.tangents, tau_t)
            rows = r[:, idx] * free[idx][None, :, :, None]  # (N, T, 4, k): the four knots' rows only
            return torch.einsum("ntfk,tf->tnk", rows, wv.to(r.dtype)), torch.einsum("ntfk,tf->tnk", rows, wd.to(r.dtype))
        tc = tau_t.clamp(k[0], k[-1])
        j = (torch.searchsorted(k, tc.detach(), right=True) - 1).clamp(0, k.numel() - 2)
        span = k[j + 1] - k[j]
        w = ((tc - k[j]) / span)[None, :, None]
        # the two knots' rows only (masked there), not the whole (N, F, k) tensor
        a, b = r[:, j] * free[j][None, :, None], r[:, j + 1] * free[j + 1][None, :, None]
        val = (a + w * (b - a)).transpose(0, 1)
        inside = ((tau_t >= k[0]) & (tau_t <= k[-1])).to(r.dtype)
        slope = ((b - a) / span[None, :, None] * inside[None, :, None]).transpose(0, 1)
        return val, slope

    def _first_layer(self, features, gamma):
        w = self.layers[0].weight
        nf = self.cfg.feature_dim
        return features @ w[:, :nf].T, gamma @ w[:, nf:].T + self.layers[0].bias

    def forward(self, tau: float | torch.Tensor, *, features: torch.Tensor | None = None,
                with_velocity: bool = False):
        """Delta A at normalised time ``tau`` for every particle: dict dp (N, 3), ds (N, 3),
        dr (N, 4); with ``with_velocity`` also 'vp' = d(Delta p)/dtau (N, 3)."""
        return {k: v[0] for k, v in self.forward_many([tau], features=features, with_velocity=with_velocity).items()}

    def forward_many(self, taus, *, features: torch.Tensor | None = None, with_velocity: bool = False):
        """Delta A at T normalised times at once (one pass of (T N) rows through the MLP; the
        features' part of the first layer is computed once): dict of (T, N, k) tensors; with
        colour residuals also 'dc' (T, N, C), the change of the degree-0 SH coefficient, with opacity
        residuals 'do' (T, N, 1), the change of the logit opacity."""
        feats = self.features if features is None else features
        n = feats.shape[0]
        keys = None  # the frozen decoder's cache keys: the times as given (python numbers only, no sync)
        if self._frozen is not None and features is None and not with_velocity and \
                not isinstance(taus, torch.Tensor) and all(isinstance(t, (int, float)) for t in taus):
            keys = [float(t) for t in taus]
        if isinstance(taus, torch.Tensor):
            tau_t = taus.to(feats.dtype).reshape(-1)
        else:  # a fill on the device, not a host-to-device copy (which would wait for the GPU)
            tau_t = torch.stack([t.to(feats.dtype).reshape(()) if isinstance(t, torch.Tensor) else
                                 torch.full((), float(t), dtype=feats.dtype, device=feats.device) for t in taus])
        between = self.cfg.time_interpolation == "knots" and self.knots is not None and \
            (with_velocity or isinstance(taus, torch.Tensor) or
             any(not isinstance(t, (int, float)) or np.abs(self._knots_np - t).min() > 1e-9 for t in taus))
        hermite = self.knots is not None and self.cfg.residual_interpolation == "hermite"
        coef = hermite_coefficients(self.knots, self.tangents, tau_t) if hermite or between else None
        if between:  # Phi at the knots, joined like the residuals (at a knot itself this is Phi there)
            mlp, vmlp = self._mlp_between_knots(tau_t, feats, with_velocity, own=features is None, coef=coef)
        elif keys is not None:
            mlp = self._frozen_mlp(keys, tau_t)
        else:
            mlp, vmlp = self._mlp(tau_t, feats, with_velocity)
        tau0 = torch.full((1,), float(self.cfg.canonical_time), dtype=feats.dtype, device=feats.device)
        coef0 = hermite_coefficients(self.knots, self.tangents, tau0) \
            if hermite and not self.cfg.canonical_residual else None
        if not hermite:
            coef = None
        out = {}
        k = 0
        for name, width in OUTPUTS.items():
            out[name] = mlp[..., k:k + width]
            if with_velocity and name == "dp":
                out["vp"] = vmlp
            if self.knots is not None:
                r, dr = self.residual_at(tau_t, name, coef)
                out[name] = out[name] + r - (0.0 if self.cfg.canonical_residual else
                                             self.residual_at(tau0, name, coef0)[0])
                if with_velocity and name == "dp":
                    out["vp"] = out["vp"] + dr
            k += width
        for name in self.appearance_outputs():
            r, _ = self.residual_at(tau_t, name, coef)
            out[name] = r if self.cfg.canonical_residual else r - self.residual_at(tau0, name, coef0)[0]
        return out

    def _mlp_between_knots(self, tau_t: torch.Tensor, feats: torch.Tensor, with_velocity: bool, own: bool,
                           coef=None):
        """(tau - tau0) Phi (T, N, outputs) for ``time_interpolation = "knots"``: Phi's output at the
        four knots around each time, weighted like the residuals (``hermite_coefficients``), and the
        position part's derivative along tau (T, N, 3) with ``with_velocity``, else None."""
        idx, wv, wd = coef if coef is not None else hermite_coefficients(self.knots, self.tangents, tau_t)
        uniq = torch.unique(idx)
        kt = self.knots[uniq]
        if self._frozen is not None and own:
            mk = self._frozen_mlp([float(x) for x in kt.tolist()], kt)
        else:
            mk, _ = self._mlp(kt, feats, False)
        g = mk[torch.searchsorted(uniq, idx)]  # (T, 4, N, outputs)
        mlp = torch.einsum("tf,tfnk->tnk", wv.to(g.dtype), g)
        vp = torch.einsum("tf,tfnk->tnk", wd.to(g.dtype), g[..., :3]) if with_velocity else None
        return mlp, vp

    def _mlp(self, tau_t: torch.Tensor, feats: torch.Tensor, with_velocity: bool):
        """(tau - tau0) Phi(theta, gamma(tau)) (T, N, outputs) and, with ``with_velocity``, the
        derivative of its position part along tau (T, N, 3), else None."""
        n = feats.shape[0]
        nt = tau_t.shape[0]
        gamma, dgamma = encode_time(tau_t, self.cfg.n_freqs, self.cfg.include_input)  # (T, D)
        # mlp_dtype (train.mlp_precision): the first and hidden layers of a training pass in lower
        # precision, the last layer in the parameters' dtype
        low = self.mlp_dtype is not None and not with_velocity and torch.is_grad_enabled()
        with torch.autocast(device_type=feats.device.type, dtype=self.mlp_dtype) if low else contextlib.nullcontext():
            a_theta, a_gamma = self._first_layer(feats, gamma)                         # (N, W), (T, W)
            h = (a_theta[None] + a_gamma[:, None]).reshape(nt * n, -1)
            dh = None
            if with_velocity:
                dh = (dgamma @ self.layers[0].weight[:, self.cfg.feature_dim:].T)[:, None].expand(nt, n, -1).reshape(nt * n, -1)
            for layer in self.layers[1:-1]:
                if with_velocity:
                    dh = layer(dh * (h > 0).to(h.dtype)) - layer.bias
                h = layer(torch.relu(h))
        last = self.layers[-1]
        if with_velocity:
            dh = (last(dh * (h > 0).to(h.dtype)) - last.bias).reshape(nt, n, -1)
        h = last(torch.relu(h).to(feats.dtype)).reshape(nt, n, -1)
        scale = (tau_t - self.cfg.canonical_time)[:, None, None]
        vp = None
        if with_velocity:  # dp is OUTPUTS' first entry
            vp = h[..., :3] + scale * dh[..., :3]
        return scale * h, vp

    # ---- a frozen Phi (the trainer's phases.freeze_decoder) ---------------------------------------
    def freeze(self, on: bool) -> None:
        """While frozen, ``forward_many`` (own features, no velocities, times given as numbers)
        computes (tau - tau0) Phi once per time and reuses it: theta and the MLP get no gradient,
        the residuals still do. Unfreezing, or new features (densify/prune), drops what was kept."""
        if not on:
            self._frozen = None
        elif self._frozen is None:
            self._frozen = {}

    @property
    def frozen(self) -> bool:
        return self._frozen is not None

    def _frozen_mlp(self, keys, tau_t: torch.Tensor) -> torch.Tensor:
        missing = [j for j, key in enumerate(keys) if key not in self._frozen]
        if missing:
            with torch.no_grad():
                new, _ = self._mlp(tau_t[missing], self.features, False)
            for j, v in zip(missing, new):
                self._frozen[keys[j]] = v
        return torch.stack([self._frozen[key] for key in keys])

    # ---- surgery (densify / prune keep theta aligned with the particles) -------------------------
    def replace_features(self, new: torch.Tensor) -> nn.Parameter:
        self.features = nn.Parameter(new.detach().clone())
        if self._frozen is not None:  # kept outputs belong to the old particles
            self._frozen = {}
        return self.features

    def set_residual(self, name: str, value: torch.Tensor) -> nn.Parameter:
        p = nn.Parameter(value.detach().clone())
        setattr(self, name, p)
        return p

    # ---- recon.h5 ------------------------------------------------------------------------------
    def to_data(self):
        from ..formats.hdf5 import DecoderData

        layers = [(lyr.weight.detach().cpu().numpy(), lyr.bias.detach().cpu().numpy()) for lyr in self.layers]
        c = self.cfg
        res = {k: v for k, v in self.residuals().items() if k[len(RESIDUAL_PREFIX):] in OUTPUTS}

        def appearance(name):  # (N, F, k) at the knots (0 at the canonical one unless canonical_residual); None when absent
            if name not in self.appearance_outputs():
                return None
            return (getattr(self, RESIDUAL_PREFIX + name) * self.knot_free[None, :, None]).detach().cpu().numpy()

        op = appearance(OPACITY_OUTPUT)
        return DecoderData(features=self.features.detach().cpu().numpy(), layers=layers,
                           encoding={"n_freqs": c.n_freqs, "include_input": c.include_input,
                                     "canonical_time": c.canonical_time, "time_scaling": "tau - tau0",
                                     "residual_interpolation": c.residual_interpolation,
                                     "time_interpolation": c.time_interpolation,
                                     **({"canonical_residual": True} if c.canonical_residual else {})},
                           outputs=dict(OUTPUTS), activation="relu",
                           residuals=None if not res else
                           torch.cat([(v * self.knot_free[None, :, None]).detach() for v in res.values()], -1).cpu().numpy(),
                           residual_knots=None if self.knots is None else self.knots.detach().cpu().numpy(),
                           color_residuals=appearance(COLOR_OUTPUT),
                           opacity_residuals=None if op is None else op[..., 0])

    @classmethod
    def from_data(cls, d, *, dtype=torch.float32, device=None) -> "Decoder":
        """From ``io.DecoderData`` (recon.h5's decoder group)."""
        if d.activation != "relu":
            raise InputError("recon.h5 decoder", f"activation {d.activation!r} is not supported (relu)")
        if dict(d.outputs) != OUTPUTS:
            raise InputError("recon.h5 decoder", f"outputs {d.outputs} differ from {OUTPUTS}")
        enc = d.encoding
        feat_dim = d.features.shape[1]
        res = getattr(d, "residuals", None)
        col = getattr(d, "color_residuals", None)
        op = getattr(d, "opacity_residuals", None)
        cfg = DecoderConfig(feature_dim=feat_dim, hidden_layers=len(d.layers) - 1,
                            hidden_width=d.layers[0][0].shape[0], n_freqs=int(enc.get("n_freqs", 0)),
                            include_input=bool(enc.get("include_input", True)),
                            canonical_time=float(enc.get("canonical_time", 0.0)), residuals=res is not None,
                            color_residuals=col is not None, opacity_residuals=op is not None,
                            residual_interpolation=residual_interpolation(enc),
                            canonical_residual=canonical_residual(enc) and res is not None,
                            time_interpolation=time_interpolation(enc))
        if d.layers[0][0].shape[1] != feat_dim + cfg.encoding_dim:
            raise InputError("recon.h5 decoder", f"first layer takes {d.layers[0][0].shape[1]} inputs; "
                                                 f"features ({feat_dim}) + encoding ({cfg.encoding_dim}) differ")
        dec = cls(d.features.shape[0], cfg, knots=None if res is None else np.asarray(d.residual_knots),
                  channels=3 if col is None else np.shape(col)[2], dtype=dtype, device=device)
        with torch.no_grad():
            dec.features.copy_(torch.as_tensor(d.features))
            k = 0
            for name, width in (OUTPUTS.items() if res is not None else ()):
                getattr(dec, RESIDUAL_PREFIX + name).copy_(torch.as_tensor(np.asarray(res)[..., k:k + width]))
                k += width
            if col is not None:
                getattr(dec, RESIDUAL_PREFIX + COLOR_OUTPUT).copy_(torch.as_tensor(np.asarray(col)))
            if op is not None:
                getattr(dec, RESIDUAL_PREFIX + OPACITY_OUTPUT).copy_(torch.as_tensor(np.asarray(op))[..., None])
            for lyr, (w, b) in zip(dec.layers, d.layers):
                if tuple(lyr.weight.shape) != tuple(w.shape):
                    raise InputError("recon.h5 decoder", f"layer shape {w.shape} != expected {tuple(lyr.weight.shape)}")
                lyr.weight.copy_(torch.as_tensor(w))
                lyr.bias.copy_(torch.as_tensor(b))
        return dec


def apply_delta(canonical: dict, delta: dict) -> dict:
    """A^t = A^0 + Delta A^t (Eq. 4) on raw parameters: means, log_scales, quats."""
    return {"means": canonical["means"] + delta["dp"],
            "log_scales": canonical["log_scales"] + delta["ds"],
            "quats": canonical["quats"] + delta["dr"]}


def mlp_low_precision(setting: str, device) -> bool:
    """Whether train.mlp_precision ``setting`` means bfloat16 on ``device``: "auto" only on a CPU
    whose oneDNN has native bf16 matrix products; elsewhere (emulated bf16, GPUs) float32."""
    if setting != "auto":
        return setting == "bfloat16"
    if torch.device(device).type != "cpu":
        return False
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


__all__ = ["hermite_coefficients", "RESIDUAL_PREFIX", "COLOR_OUTPUT", "OPACITY_OUTPUT", "Decoder", "DecoderConfig", "TimeMap", "encode_time", "apply_delta", "OUTPUTS"]
