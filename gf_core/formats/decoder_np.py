"""The time-continuous decoder (paper Eq. 4) in numpy, for places without torch (the Blender extension).

Same function as ``gf_core.recon.decoder.Decoder`` (a test holds the two equal to 1e-5):

    A^t = A^0 + (tau - tau0) * Phi(theta, gamma(tau))                                   (Eq. 4)

plus, when the reconstruction has them, the residuals R(tau) - R(tau0) (R(tau) where the
canonical frame has residuals of its own, encoding ``canonical_residual``) between knots (cubic
Hermite with three-point tangents, ``hermite_coefficients``; files written before it: linear),
and the appearance residuals (the same on the degree-0 SH coefficient, output ``dc``, and on the
logit opacity, output ``do``).

with gamma(tau) = [tau, sin(2^k pi tau), cos(2^k pi tau)], k = 0..L-1, and Phi an MLP with ReLU
between its layers. Float32, vectorised over particles: the first layer's theta part,
theta @ W_theta^T, does not depend on time and is computed once per reconstruction; each time then
costs the hidden layers only, evaluated in blocks of particles so that the intermediate
activations stay in cache. Velocities dp/dt are forward-mode derivatives along tau (the ReLU
masks of the forward pass), as in the torch decoder.

Imports numpy only (``io`` for ``from_recon`` needs h5py only when reading a file).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

OUTPUTS = {"dp": 3, "ds": 3, "dr": 4}  # position, log-scale, quaternion changes (as gf_core.recon.decoder)
# how the residuals R are interpolated between their knots: "hermite" (C1: positions and velocities
# continuous across the training frames) or "linear" (recon.h5 files that do not name one)
RESIDUAL_INTERPOLATIONS = ("hermite", "linear")
# between the knots, Phi itself: "decoder" (evaluated at tau, Eq. 4; files that do not name one) or
# "knots" (evaluated at the knots and joined by the residuals' Hermite segments)
TIME_INTERPOLATIONS = ("decoder", "knots")


def hermite_coefficients(knots: np.ndarray, tau: float):
    """R(tau) and dR/dtau as weights on four knot values, for residuals interpolated with cubic
    Hermite segments whose tangents m_j are the three-point derivatives at the interior knots, so
    that a quadratic in time, such as free fall, is reproduced with its exact velocity away from the
    clip's ends, and the chords at the first and last knot:

        interior:  m_j = -h1 / (h0 (h0 + h1)) R_{j-1} + (h1 - h0) / (h0 h1) R_j + h0 / (h1 (h0 + h1)) R_{j+1}
        first:     m_0 = (R_1 - R_0) / h1;  last: m_{F-1} = (R_{F-1} - R_{F-2}) / h_{F-2}
        (h0 = k_j - k_{j-1}, h1 = k_{j+1} - k_j)
        R(tau) = H00(s) R_j + H10(s) h1 m_j + H01(s) R_{j+1} + H11(s) h1 m_{j+1},  s = (tau - k_j) / h1

    Returns (indices (4,) of knots j-1..j+2 clamped to the knots, value weights (4,), derivative
    weights (4,)); constant outside the knots (derivative 0). The torch decoder evaluates the same
    expressions on tensors (``gf_core.recon.decoder.hermite_coefficients``)."""
    k = np.asarray(knots, np.float64)
    f = len(k)
    tc = min(max(float(tau), k[0]), k[-1])
    j = int(np.clip(np.searchsorted(k, tc, side="right") - 1, 0, f - 2))
    h1 = k[j + 1] - k[j]
    m_j, m_j1 = tangent_weights(k, j, j), tangent_weights(k, j + 1, j)
    s = (tc - k[j]) / h1  # (the torch decoder takes m_j, m_j1 from tangent_table)
    H = (2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s, -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2)
    inside = k[0] <= tau <= k[-1]
    dH = [x / h1 if inside else 0.0 for x in (6 * s ** 2 - 6 * s, 3 * s ** 2 - 4 * s + 1, -6 * s ** 2 + 6 * s,
                                              3 * s ** 2 - 2 * s)]

    def weights(h00, h10, h01, h11):
        return np.array([0.0, h00, h01, 0.0]) + h1 * (h10 * m_j + h11 * m_j1)

    idx = np.clip(np.arange(j - 1, j + 3), 0, f - 1)
    return idx, weights(*H), weights(*dH)


def tangent_table(knots) -> np.ndarray:
    """(F - 1, 2, 4): for each segment j, the tangents m_j and m_{j+1} as weights on its four knots
    j-1..j+2 (``tangent_weights``)."""
    k = np.asarray(knots, np.float64)
    return np.array([[tangent_weights(k, j, j), tangent_weights(k, j + 1, j)] for j in range(len(k) - 1)])


def tangent_weights(k: np.ndarray, i: int, j: int) -> np.ndarray:
    """The tangent m_i at knot ``i`` (``hermite_coefficients``) as weights on the four knots
    j-1..j+2 around segment ``j`` (``i`` is j or j + 1)."""
    f = len(k)
    w = np.zeros(4)
    o = i - j + 1  # slot of knot i in the stencil j-1..j+2
    if f == 2:
        w[1], w[2] = -1.0 / (k[1] - k[0]), 1.0 / (k[1] - k[0])
    elif i == 0:  # the chord (a second-order one-sided difference amplifies noise fourfold here)
        w[o], w[o + 1] = -1.0 / (k[1] - k[0]), 1.0 / (k[1] - k[0])
    elif i == f - 1:
        w[o - 1], w[o] = -1.0 / (k[f - 1] - k[f - 2]), 1.0 / (k[f - 1] - k[f - 2])
    else:
        h0, h1 = k[i] - k[i - 1], k[i + 1] - k[i]
        w[o - 1:o + 2] = (-h1 / (h0 * (h0 + h1)), (h1 - h0) / (h0 * h1), h0 / (h1 * (h0 + h1)))
    return w


@dataclass
class TimeMap:
    """Seconds <-> normalised time tau in [0, 1] over the training clip [t_min, t_max]."""

    t_min: float
    t_max: float
    policy: str = "clamp"  # times outside the clip: "clamp" (with a warning) or "error"

    def __post_init__(self):
        if self.policy not in ("clamp", "error"):
            raise InputError("time map", f"unknown out-of-range policy {self.policy!r} (clamp, error)")

    @property
    def duration(self) -> float:
        return max(self.t_max - self.t_min, 0.0)

    def inside(self, t: float) -> bool:
        return self.t_min - 1e-9 * max(1.0, self.duration) <= float(t) <= self.t_max + 1e-9 * max(1.0, self.duration)

    def tau(self, t: float, *, warn: bool = True) -> float:
        if self.duration <= 0:
            return 0.0
        tau = (float(t) - self.t_min) / self.duration
        if tau < -1e-9 or tau > 1 + 1e-9:
            msg = f"time {t:.6g} s is outside the reconstructed clip [{self.t_min:.6g}, {self.t_max:.6g}] s"
            if self.policy == "error":
                raise InputError("decoder", msg)
            if warn:
                warnings.warn(msg + "; clamped to the clip (the decoder does not extrapolate)", RuntimeWarning,
                              stacklevel=3)
        return min(max(tau, 0.0), 1.0)


def encode_time(tau: float, n_freqs: int, include_input: bool = True):
    """gamma(tau) (D,) and d gamma / d tau (D,), float64."""
    parts, dparts = [], []
    if include_input:
        parts.append([tau])
        dparts.append([1.0])
    if n_freqs > 0:
        w = math.pi * 2.0 ** np.arange(n_freqs)
        parts += [np.sin(tau * w), np.cos(tau * w)]
        dparts += [np.cos(tau * w) * w, -np.sin(tau * w) * w]
    return np.concatenate(parts), np.concatenate(dparts)


class NumpyDecoder:
    """Phi from ``io.DecoderData`` (recon.h5's decoder group), evaluated with numpy float32."""

    def __init__(self, data, *, block: int = 8192):
        if data.activation != "relu":
            raise InputError("recon.h5 decoder", f"activation {data.activation!r} is not supported (relu)")
        if dict(data.outputs) != OUTPUTS:
            raise InputError("recon.h5 decoder", f"outputs {data.outputs} differ from {OUTPUTS}")
        enc = data.encoding
        self.n_freqs = int(enc.get("n_freqs", 0))
        self.include_input = bool(enc.get("include_input", True))
        self.canonical_time = float(enc.get("canonical_time", 0.0))
        feats = np.ascontiguousarray(data.features, np.float32)
        nf = feats.shape[1]
        enc_dim = (1 if self.include_input else 0) + 2 * self.n_freqs
        w0 = np.asarray(data.layers[0][0], np.float32)
        if w0.shape[1] != nf + enc_dim:
            raise InputError("recon.h5 decoder", f"first layer takes {w0.shape[1]} inputs; features ({nf}) + "
                                                 f"encoding ({enc_dim}) differ")
        self.w_gamma = w0[:, nf:]
        self.b0 = np.asarray(data.layers[0][1], np.float32)
        # time-independent part of the first layer, once per reconstruction
        self.a_theta = feats @ w0[:, :nf].T
        # later layers stored transposed (in, out) so that rows of particles multiply on the left
        self.layers = [(np.ascontiguousarray(np.asarray(w, np.float32).T), np.asarray(b, np.float32))
                       for w, b in data.layers[1:]]
        self.block = int(block)
        # optional residuals (recon.h5 version 2): R at the knots, linear in tau between them, so that
        # Delta A = (tau - tau0) Phi + R(tau) - R(tau0)
        self.residuals = None if getattr(data, "residuals", None) is None else \
            np.ascontiguousarray(data.residuals, np.float32)
        self.interpolation = residual_interpolation(enc)
        self.time_interpolation = time_interpolation(enc)
        self._at_knot = {}  # time_interpolation "knots": (tau - tau0) Phi at each knot, computed once
        self.knots = None if self.residuals is None else np.asarray(data.residual_knots, np.float64)
        # R(tau) - R(tau0), R 0 at the canonical knot; or R(tau) with residuals of the canonical frame's own
        self.canonical_residual = self.residuals is not None and canonical_residual(enc)
        free = None if self.residuals is None else \
            np.ones((1, len(self.knots), 1), np.float32) if self.canonical_residual else \
            (np.abs(self.knots - self.canonical_time) > 1e-6)[None, :, None]
        if self.residuals is not None:
            self.residuals = self.residuals * free
        # optional appearance residuals (recon.h5 version 3): the same knots, on the degree-0 SH
        # coefficient (colour) and on the logit opacity
        col, op = getattr(data, "color_residuals", None), getattr(data, "opacity_residuals", None)
        self.color_residuals = None if col is None or free is None else np.ascontiguousarray(col, np.float32) * free
        self.opacity_residuals = None if op is None or free is None else \
            np.ascontiguousarray(op, np.float32)[..., None] * free

    def _residual(self, tau: float, values=None):
        """R(tau) (N, k) and dR/dtau (N, k) of ``values`` (N, F, k; default the pose residuals);
        constant (slope 0) outside the knots."""
        values = self.residuals if values is None else values
        k = self.knots
        if self.interpolation == "hermite":
            idx, wv, wd = hermite_coefficients(k, tau)
            rows = values[:, idx]  # (N, 4, k)
            return np.einsum("nfk,f->nk", rows, wv.astype(np.float32)), \
                np.einsum("nfk,f->nk", rows, wd.astype(np.float32))
        tc = min(max(tau, k[0]), k[-1])
        j = int(np.clip(np.searchsorted(k, tc, side="right") - 1, 0, len(k) - 2))
        span = k[j + 1] - k[j]
        w = np.float32((tc - k[j]) / span)
        a, b = values[:, j], values[:, j + 1]
        slope = (b - a) * np.float32(1.0 / span) if k[0] <= tau <= k[-1] else np.zeros_like(a)
        return a + w * (b - a), slope

    @property
    def num_particles(self) -> int:
        return self.a_theta.shape[0]

    def __call__(self, tau: float, *, with_velocity: bool = False) -> dict:
        """Delta A at normalised time ``tau``: dp (N, 3), ds (N, 3), dr (N, 4) float32; with
        ``with_velocity`` also 'vp' = d(Delta p)/dtau (N, 3); with colour residuals also 'dc'
        (N, channels), the change of the degree-0 SH coefficient; with opacity residuals 'do' (N, 1),
        the change of the logit opacity."""
        tau = float(tau)
        if self.time_interpolation == "knots" and self.residuals is not None and \
                (with_velocity or np.abs(self.knots - tau).min() > 1e-9):
            idx, wv, wd = hermite_coefficients(self.knots, tau)
            rows = [self._knot_output(int(j)) for j in idx]
            out = sum(np.float32(w) * r for w, r in zip(wv, rows))
            vel = sum(np.float32(w) * r[:, :3] for w, r in zip(wd, rows)) if with_velocity else None
        else:
            out, vel = self._scaled_mlp(tau, with_velocity)
        return self._with_residuals(tau, out, vel, with_velocity)

    def _knot_output(self, j: int) -> np.ndarray:
        if j not in self._at_knot:
            self._at_knot[j] = self._scaled_mlp(float(self.knots[j]), False)[0]
        return self._at_knot[j]

    def _scaled_mlp(self, tau: float, with_velocity: bool):
        """(tau - tau0) Phi (N, outputs) and, with ``with_velocity``, its position part's derivative
        along tau (N, 3), else None."""
        gamma, dgamma = encode_time(tau, self.n_freqs, self.include_input)
        row = (self.w_gamma @ gamma.astype(np.float32) + self.b0).astype(np.float32)
        drow = (self.w_gamma @ dgamma.astype(np.float32)).astype(np.float32)
        n = self.num_particles
        width = sum(OUTPUTS.values())
        out = np.empty((n, width), np.float32)
        vel = np.empty((n, 3), np.float32) if with_velocity else None
        scale = np.float32(tau - self.canonical_time)
        for s in range(0, n, self.block):
            h = self.a_theta[s:s + self.block] + row
            m = len(h)
            if with_velocity:
                # forward-mode: the tangent rows dh ride below the activations in the same product
                x = np.empty((2 * m, h.shape[1]), np.float32)
                x[m:] = drow
                for w_t, b in self.layers:
                    mask = h > 0
                    np.multiply(h, mask, out=x[:m])  # ReLU (h is x[:m] after the first layer)
                    x[m:] *= mask
                    x = x @ w_t
                    h = x[:m]
                    h += b
                dh = x[m:]
                # d/dtau [(tau - tau0) Phi_p] = Phi_p + (tau - tau0) dPhi_p/dtau
                vel[s:s + m] = h[:, :3] + scale * dh[:, :3]
            else:
                for w_t, b in self.layers:
                    np.maximum(h, 0, out=h)
                    h = h @ w_t
                    h += b
            out[s:s + m] = h
        out *= scale
        return out, vel

    def _with_residuals(self, tau: float, out: np.ndarray, vel, with_velocity: bool) -> dict:
        if self.residuals is not None:
            r, slope = self._residual(tau)
            out += r if self.canonical_residual else r - self._residual(self.canonical_time)[0]
            if with_velocity:
                vel += slope[:, :3]
        res, k = {}, 0
        for name, w in OUTPUTS.items():
            res[name] = out[:, k:k + w]
            k += w
        if with_velocity:
            res["vp"] = vel
        for name, values in (("dc", self.color_residuals), ("do", self.opacity_residuals)):
            if values is not None:
                r = self._residual(tau, values)[0]
                res[name] = r if self.canonical_residual else r - self._residual(self.canonical_time, values)[0]
        return res


def canonical_residual(encoding: dict) -> bool:
    """Whether a decoder's encoding (recon.h5) gives the canonical frame residuals of its own
    (Delta A = (tau - tau0) Phi + R(tau)); False when absent (R(tau) - R(tau0))."""
    v = encoding.get("canonical_residual", False)
    if not isinstance(v, (bool, np.bool_)):
        raise InputError("recon.h5 decoder", f"canonical_residual {v!r} is not true or false")
    return bool(v)


def residual_interpolation(encoding: dict) -> str:
    """The residuals' interpolation named in a decoder's encoding (recon.h5); "linear" when absent."""
    v = encoding.get("residual_interpolation", "linear")
    if v not in RESIDUAL_INTERPOLATIONS:
        raise InputError("recon.h5 decoder", f"residual_interpolation {v!r} is not one of {', '.join(RESIDUAL_INTERPOLATIONS)}")
    return v


def time_interpolation(encoding: dict) -> str:
    """Phi's interpolation between the knots named in a decoder's encoding; "decoder" when absent."""
    v = encoding.get("time_interpolation", "decoder")
    if v not in TIME_INTERPOLATIONS:
        raise InputError("recon.h5 decoder", f"time_interpolation {v!r} is not one of {', '.join(TIME_INTERPOLATIONS)}")
    return v


def centre_box(lo, hi, inset: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the particle centres: the scene box ``lo``..``hi`` shrunk by ``inset`` metres on
    every face (``recon.h5``'s ``config.bounds.inset``, model.wall_inset; a face pair closer than
    twice the inset meets in the middle)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    d = np.minimum(float(inset), 0.5 * (hi - lo))
    return lo + d, hi - d


def unit_quaternions(q) -> np.ndarray:
    """Quaternions w x y z (N, 4) of any norm as unit ones (a zero one becomes the identity)."""
    q = np.asarray(q, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0, 0, 0]))


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float32)))


SH_C0 = 0.28209479177387814  # degree-0 spherical-harmonic constant, as the renderer's


def base_color(sh_dc) -> np.ndarray:
    """(N, 3) view-independent colour in [0, 1] of degree-0 SH coefficients (N, channels), as the
    renderer evaluates it (grayscale repeated over RGB)."""
    c = SH_C0 * np.asarray(sh_dc, np.float32) + 0.5
    return np.clip(np.repeat(c, 3, axis=1) if c.shape[1] == 1 else c, 0.0, 1.0)


class ParticleAnimation:
    """A reconstruction (``io.ReconData``) as particles at any time in seconds: positions, scales,
    velocities, colours. A static reconstruction (no decoder) gives its canonical particles at
    every time."""

    def __init__(self, recon, *, policy: str = "clamp", source: str | None = None):
        self.recon = recon
        self.source = source  # the file it came from, if any
        self.time = TimeMap(float(recon.time_min), float(recon.time_max), policy)
        self.decoder = NumpyDecoder(recon.decoder) if recon.decoder is not None else None
        self.means = np.ascontiguousarray(recon.means, np.float32)
        self.log_scales = np.ascontiguousarray(recon.log_scales, np.float32)
        self.quats = np.ascontiguousarray(recon.quats, np.float32)
        # the domain the trainer keeps particles in (FluidModel: means clamped to the box inset by
        # bounds.inset, log-scales to their range), when recon.h5 records it
        b = (recon.config or {}).get("bounds")
        self.bounds = None
        if b:
            lo, hi = centre_box(b["lo"], b["hi"], b.get("inset", 0.0))
            self.bounds = (lo.astype(np.float32), hi.astype(np.float32),
                           np.float32(b["log_scale_min"]), np.float32(b["log_scale_max"]))
        self.logit_opacity = np.asarray(recon.logit_opacity, np.float32)
        self.opacity = sigmoid(self.logit_opacity)  # at the canonical time (opacity residuals change it in time)
        self.sh = np.asarray(recon.sh, np.float32)
        self.color = base_color(self.sh[:, 0, :])  # at the canonical time (colour residuals change it in time)

    @property
    def color_varies(self) -> bool:
        """True when the colour changes in time (colour residuals)."""
        return self.decoder is not None and self.decoder.color_residuals is not None

    @property
    def opacity_varies(self) -> bool:
        """True when the opacity changes in time (opacity residuals)."""
        return self.decoder is not None and self.decoder.opacity_residuals is not None

    @property
    def num_particles(self) -> int:
        return self.means.shape[0]

    def at(self, t: float, *, velocity: bool = False, warn: bool = True) -> dict:
        """positions (N, 3), log_scales (N, 3), quats (N, 4, as stored: not normalised), sh (N, K,
        channels), colors (N, 3: the view-independent base colour in [0, 1]), logit_opacity and
        opacities (N,) and, with ``velocity``,
        velocities (N, 3) in scene units per second, at time ``t`` (seconds; outside the clip:
        clamped, velocity 0)."""
        inside = self.time.inside(t)
        tau = self.time.tau(t, warn=warn)
        d = self.decoder(tau, with_velocity=velocity) if self.decoder is not None else None
        if d is None:  # static: the canonical particles at every time
            pos, ls, q = self.means, self.log_scales, self.quats
        else:
            pos, ls, q = self.means + d["dp"], self.log_scales + d["ds"], self.quats + d["dr"]
        held = None
        if self.bounds is not None:
            lo, hi, smin, smax = self.bounds
            raw, pos = pos, np.minimum(np.maximum(pos, lo), hi)
            held = pos != raw  # coordinates held at a wall: their velocity is 0 (the clamp's derivative)
            ls = np.clip(ls, smin, smax)
        sh, colors = self.sh, self.color
        if d is not None and "dc" in d:
            sh = self.sh.copy()
            sh[:, 0, :] += d["dc"]
            colors = base_color(sh[:, 0, :])
        logit = self.logit_opacity
        if d is not None and "do" in d:
            logit = self.logit_opacity + d["do"][:, 0]
        out = {"positions": pos, "log_scales": ls, "quats": q, "sh": sh, "colors": colors,
               "logit_opacity": logit, "opacities": self.opacity if logit is self.logit_opacity else sigmoid(logit)}
        if velocity:
            if d is None or self.time.duration <= 0 or not inside:
                out["velocities"] = np.zeros_like(self.means)
            else:
                v = d["vp"] / np.float32(self.time.duration)
                out["velocities"] = v if held is None else np.where(held, np.float32(0), v)
        return out

__all__ = ["NumpyDecoder", "ParticleAnimation", "base_color", "centre_box", "hermite_coefficients", "tangent_table", "residual_interpolation", "time_interpolation",
           "TIME_INTERPOLATIONS",
           "RESIDUAL_INTERPOLATIONS", "TimeMap", "encode_time", "OUTPUTS", "SH_C0"]
