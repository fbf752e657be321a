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

The numpy twin in ``gf_core/decoder_np.py`` (used by the Blender extension, which has no torch)
evaluates the same function; a test holds the two equal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

# TimeMap (seconds <-> tau) and the output layout are shared with the numpy twin, which needs no torch
from .decoder_np import OUTPUTS, TimeMap
from .errors import InputError


@dataclass
class DecoderConfig:
    feature_dim: int = 64        # N_theta (paper Sec. 4.1.2)
    hidden_layers: int = 4       # paper: 4 hidden layers
    hidden_width: int = 256      # paper: 256 neurons per layer
    n_freqs: int = 6             # L of gamma(tau)
    include_input: bool = True   # tau itself in gamma(tau)
    canonical_time: float = 0.0  # tau0 in [0, 1]

    def validate(self) -> "DecoderConfig":
        for k in ("feature_dim", "hidden_layers", "hidden_width"):
            if int(getattr(self, k)) < 1:
                raise InputError("decoder config", f"{k} must be >= 1, got {getattr(self, k)}")
        if int(self.n_freqs) < 0:
            raise InputError("decoder config", f"n_freqs must be >= 0, got {self.n_freqs}")
        if not 0.0 <= float(self.canonical_time) <= 1.0:
            raise InputError("decoder config", f"canonical_time must be in [0, 1], got {self.canonical_time}")
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


class Decoder(nn.Module):
    """Phi: per-particle features theta (N, N_theta) and the shared MLP.

    The first layer's weight is split into its theta part and its gamma part, so that the time
    encoding is multiplied once per time, not once per particle.
    """

    def __init__(self, num_particles: int, cfg: DecoderConfig | None = None, *, dtype=torch.float32,
                 device=None):
        super().__init__()
        self.cfg = (cfg or DecoderConfig()).validate()
        c = self.cfg
        # theta starts at zero (paper: "both are initialised to zero"); the hidden layers get the
        # default init so that gradients reach theta once the last layer moves away from zero.
        self.features = nn.Parameter(torch.zeros(num_particles, c.feature_dim, dtype=dtype, device=device))
        widths = [c.feature_dim + c.encoding_dim] + [c.hidden_width] * c.hidden_layers
        layers = [nn.Linear(a, b, dtype=dtype, device=device) for a, b in zip(widths[:-1], widths[1:])]
        last = nn.Linear(widths[-1], sum(OUTPUTS.values()), dtype=dtype, device=device)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.layers = nn.ModuleList(layers + [last])

    @property
    def num_particles(self) -> int:
        return self.features.shape[0]

    def mlp_parameters(self):
        return list(self.layers.parameters())

    def _first_layer(self, features, gamma):
        w = self.layers[0].weight
        nf = self.cfg.feature_dim
        return features @ w[:, :nf].T, gamma @ w[:, nf:].T + self.layers[0].bias

    def forward(self, tau: float | torch.Tensor, *, features: torch.Tensor | None = None,
                with_velocity: bool = False):
        """Delta A at normalised time ``tau`` for every particle: dict dp (N, 3), ds (N, 3),
        dr (N, 4); with ``with_velocity`` also 'vp' = d(Delta p)/dtau (N, 3)."""
        feats = self.features if features is None else features
        # a fill on the device, not a host-to-device copy (which would wait for the GPU)
        tau_t = tau.to(feats.dtype).reshape(()) if isinstance(tau, torch.Tensor) else \
            torch.full((), float(tau), dtype=feats.dtype, device=feats.device)
        gamma, dgamma = encode_time(tau_t, self.cfg.n_freqs, self.cfg.include_input)
        a_theta, a_gamma = self._first_layer(feats, gamma)
        h = a_theta + a_gamma
        dh = None
        if with_velocity:
            dh = (dgamma @ self.layers[0].weight[:, self.cfg.feature_dim:].T).expand_as(h)
        for layer in self.layers[1:]:
            if with_velocity:
                mask = (h > 0).to(h.dtype)
                dh = layer(dh * mask) - layer.bias
            h = layer(torch.relu(h))
        scale = tau_t - self.cfg.canonical_time
        out = {}
        k = 0
        for name, width in OUTPUTS.items():
            out[name] = scale * h[:, k:k + width]
            if with_velocity and name == "dp":
                out["vp"] = h[:, k:k + width] + scale * dh[:, k:k + width]
            k += width
        return out

    # ---- surgery (densify / prune keep theta aligned with the particles) -------------------------
    def replace_features(self, new: torch.Tensor) -> None:
        self.features = nn.Parameter(new.detach().clone())

    # ---- recon.h5 ------------------------------------------------------------------------------
    def to_data(self):
        from .io import DecoderData

        layers = [(lyr.weight.detach().cpu().numpy(), lyr.bias.detach().cpu().numpy()) for lyr in self.layers]
        c = self.cfg
        return DecoderData(features=self.features.detach().cpu().numpy(), layers=layers,
                           encoding={"n_freqs": c.n_freqs, "include_input": c.include_input,
                                     "canonical_time": c.canonical_time, "time_scaling": "tau - tau0"},
                           outputs=dict(OUTPUTS), activation="relu")

    @classmethod
    def from_data(cls, d, *, dtype=torch.float32, device=None) -> "Decoder":
        """From ``io.DecoderData`` (recon.h5's decoder group)."""
        if d.activation != "relu":
            raise InputError("recon.h5 decoder", f"activation {d.activation!r} is not supported (relu)")
        if dict(d.outputs) != OUTPUTS:
            raise InputError("recon.h5 decoder", f"outputs {d.outputs} differ from {OUTPUTS}")
        enc = d.encoding
        feat_dim = d.features.shape[1]
        cfg = DecoderConfig(feature_dim=feat_dim, hidden_layers=len(d.layers) - 1,
                            hidden_width=d.layers[0][0].shape[0], n_freqs=int(enc.get("n_freqs", 0)),
                            include_input=bool(enc.get("include_input", True)),
                            canonical_time=float(enc.get("canonical_time", 0.0)))
        if d.layers[0][0].shape[1] != feat_dim + cfg.encoding_dim:
            raise InputError("recon.h5 decoder", f"first layer takes {d.layers[0][0].shape[1]} inputs; "
                                                 f"features ({feat_dim}) + encoding ({cfg.encoding_dim}) differ")
        dec = cls(d.features.shape[0], cfg, dtype=dtype, device=device)
        with torch.no_grad():
            dec.features.copy_(torch.as_tensor(d.features))
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


__all__ = ["Decoder", "DecoderConfig", "TimeMap", "encode_time", "apply_delta", "OUTPUTS"]
