"""Densify and prune (paper Fig. 2(d), "improved density optimisation"), as small strategy
objects in the shape of gsplat's ``Strategy``: its own config (``DensifyConfig``, the presets'
``[densify]``), ``step_post_backward`` after every backward pass and ``refine`` after every step;
the strategy edits the particle set, keeping the optimiser's state
aligned with the particles (``ParticleOptimizer.surgery``).

``DensifyPrune`` (3DGS's adaptive density control):
- accumulates, per particle, the norm of the 2D mean gradient in NDC units (the pixel gradient
  times (W/2, H/2)) over the views where it was drawn;
- every ``every`` iterations inside [start, stop): particles whose mean gradient exceeds
  ``grad_threshold`` are cloned when small (largest scale <= ``clone_max_scale`` particle
  spacings) or split in two when large (samples of the Gaussian, scales / 1.6);
- prunes particles with opacity below ``prune_opacity``, larger than ``prune_max_scale`` spacings,
  or outside the domain (decoded particles are clamped into it by the model);
- never grows past ``max_particles`` (the highest gradients win) and never prunes the last one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..render.reference import quat_to_rotmat
from .model import FluidModel


class ParticleOptimizer:
    """One Adam per parameter group; per-particle tensors can be cut and grown in place."""

    def __init__(self, model: FluidModel, lrs: dict[str, float], *, mlp_lr: float = 0.0, eps: float = 1e-15,
                 betas: dict[str, tuple[float, float]] | None = None):
        self.model = model
        self.lrs = dict(lrs)
        self.eps = eps
        betas = betas or {}
        groups = [{"params": [p], "lr": self.lrs.get(name, 0.0), "name": name,
                   **({"betas": betas[name]} if name in betas else {})}
                  for name, p in model.per_particle().items()]
        if model.decoder is not None:
            groups.append({"params": model.decoder.mlp_parameters(), "lr": mlp_lr, "name": "mlp"})
        # on CUDA the fused kernel updates a group in one launch instead of a dozen (same Adam)
        fused = all(q.is_cuda and q.dtype == torch.float32 for g in groups for q in g["params"])
        self.opt = torch.optim.Adam(groups, eps=eps, fused=fused or None)

    def group(self, name: str) -> dict:
        for g in self.opt.param_groups:
            if g["name"] == name:
                return g
        raise KeyError(name)

    def set_lr(self, name: str, lr: float) -> None:
        self.group(name)["lr"] = lr

    def zero_grad(self) -> None:
        self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.opt.step()

    def state_dict(self) -> dict:
        return self.opt.state_dict()

    def load_state_dict(self, sd: dict) -> None:
        self.opt.load_state_dict(sd)

    @torch.no_grad()
    def surgery(self, keep: torch.Tensor, new: dict[str, torch.Tensor] | None = None) -> None:
        """Keep the particles where ``keep`` is True and append ``new`` (a value per per-particle
        name, same rows); Adam's moments follow (kept rows keep theirs, new rows start at zero)."""
        for g in self.opt.param_groups:
            name = g["name"]
            if name == "mlp":
                continue
            old = g["params"][0]
            value = old[keep]
            if new:
                value = torch.cat([value, new[name].to(old.dtype)], 0)
            p = self.model.set_per_particle(name, value)
            st = self.opt.state.pop(old, None)
            if st:
                for k in ("exp_avg", "exp_avg_sq"):
                    m = st[k][keep]
                    if new:
                        m = torch.cat([m, torch.zeros_like(new[name], dtype=m.dtype)], 0)
                    st[k] = m
                self.opt.state[p] = st
            g["params"][0] = p
        for name, old in self.model.per_particle_fixed().items():  # not optimised: rows only
            value = old[keep]
            if new:
                value = torch.cat([value, new[name].to(old.dtype)], 0)
            self.model.set_per_particle(name, value)


@dataclass
class DensifyConfig:
    """``[densify]`` of the presets (every key documented in ``presets/water.toml``)."""

    enabled: bool = True
    phases: list = field(default_factory=lambda: [1, 2])
    start: int = 200               # first refinement, iterations into the phase
    every: int = 100               # refinement interval
    stop_fraction: float = 0.8     # no refinement in the last 20% of a phase
    grad_threshold: float = 6e-5   # mean |dL/d mean2d| in NDC units
    clone_max_scale: float = 0.5   # in particle spacings: at most this is cloned, larger split
    prune_opacity: float = 0.005
    prune_max_scale: float = 3.0   # in particle spacings


def make_optimizer(cfg, model: FluidModel) -> tuple[ParticleOptimizer, dict]:
    """The run's optimiser and its base rates (``[lr]``): the means' rate scaled by the box's
    diagonal (3DGS's scene extent), each residual group at ``lr.residuals`` x the rate of what it
    corrects (means, log scales, quaternions, base colour, opacity) with Adam's beta1
    ``lr.residuals_beta1``, the decoder's MLP at ``lr.mlp``."""
    lr = cfg.lr
    lrs = {"means": lr.means * model.bounds.extent, "log_scales": lr.log_scales, "quats": lr.quats,
           "logit_opacity": lr.logit_opacity, "sh_dc": lr.sh_dc, "sh_rest": lr.sh_rest}
    dec = model.decoder
    if dec is not None:
        lrs["features"] = lr.features
        for name in dec.residuals():
            base = {"dp": "means", "ds": "log_scales", "dr": "quats", "dc": "sh_dc",
                    "do": "logit_opacity"}[name[len("residual_"):]]
            lrs[name] = lr.residuals * lrs[base]
    betas = {name: (lr.residuals_beta1, 0.999) for name in lrs if name.startswith("residual_")}
    return ParticleOptimizer(model, lrs, mlp_lr=lr.mlp, betas=betas), lrs


@dataclass
class DensifyPrune:
    cfg: DensifyConfig
    max_particles: int = 100_000
    split_factor: float = 1.6
    reset_opacity_every: int = 0    # 3DGS resets opacities to catch floaters; 0 = never
    reset_opacity_value: float = 0.01
    state: dict = field(default_factory=dict)

    def active(self, phase: int) -> bool:
        return self.cfg.enabled and phase in self.cfg.phases

    def reset(self, n: int, device) -> None:
        self.state = {"grad": torch.zeros(n, device=device), "count": torch.zeros(n, device=device)}

    def step_post_backward(self, means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Accumulate one view's 2D mean gradient (call after ``backward`` per rendered view)."""
        if means2d.grad is None:
            return
        if not self.state or self.state["grad"].shape[0] != means2d.shape[0]:
            self.reset(means2d.shape[0], means2d.device)
        g = means2d.grad.detach().clone()
        g[:, 0] *= 0.5 * width
        g[:, 1] *= 0.5 * height
        vis = radii > 0  # masked arithmetic, not boolean indexing: no device synchronisation
        self.state["grad"] += torch.where(vis, g.norm(dim=-1), 0.0).to(self.state["grad"].dtype)
        self.state["count"] += vis.to(self.state["count"].dtype)

    @torch.no_grad()
    def refine(self, it: int, stop: int, model: FluidModel, opt: ParticleOptimizer, spacing: float, *,
               generator: torch.Generator | None = None) -> dict:
        """Densify and prune if ``it`` (iterations into the phase) is a refinement iteration before
        ``stop``. Returns what it did."""
        c = self.cfg
        report = {}
        if not (c.start <= it < stop) or it % c.every != 0 or not self.state:
            return report
        n = len(model)
        dev = model.means.device
        scales = torch.exp(model.log_scales)
        max_s = scales.max(-1).values
        avg = self.state["grad"] / self.state["count"].clamp_min(1)
        cand = (avg > c.grad_threshold) & (self.state["count"] > 0)
        room = max(self.max_particles - n, 0)
        if int(cand.sum()) > room:  # the budget: the strongest gradients win (a split adds one net)
            keep_idx = torch.topk(torch.where(cand, avg, torch.full_like(avg, -1.0)), room).indices
            cand = torch.zeros_like(cand)
            cand[keep_idx] = True
        clone = cand & (max_s <= c.clone_max_scale * spacing)
        split = cand & ~clone
        new = {}
        per = {**model.per_particle(), **model.per_particle_fixed()}
        if clone.any() or split.any():
            parts = {k: [] for k in per}
            if clone.any():
                for k, p in per.items():
                    parts[k].append(p[clone])
            if split.any():
                idx = torch.nonzero(split).flatten()
                R = quat_to_rotmat(model.quats[idx])
                s = scales[idx]
                for _ in range(2):
                    z = torch.randn(idx.numel(), 3, dtype=s.dtype, generator=generator).to(dev)
                    off = (R @ (s * z)[..., None])[..., 0]
                    for k, p in per.items():
                        v = p[idx]
                        if k == "means":
                            v = v + off
                        elif k == "log_scales":
                            v = v - math.log(self.split_factor)
                        parts[k].append(v)
            new = {k: torch.cat(v, 0) for k, v in parts.items()}
        # the split originals are replaced by their two halves
        keep = ~split
        prune = torch.sigmoid(model.logit_opacity) < c.prune_opacity
        prune |= max_s > c.prune_max_scale * spacing
        clo, chi = model.bounds.centre_box()
        lo = torch.tensor(clo, device=dev, dtype=model.means.dtype)
        hi = torch.tensor(chi, device=dev, dtype=model.means.dtype)
        prune |= ((model.means < lo) | (model.means > hi)).any(-1) | ~torch.isfinite(model.means).all(-1)
        if int((keep & ~prune).sum()) + (next(iter(new.values())).shape[0] if new else 0) < 1:
            prune[torch.argmax(torch.sigmoid(model.logit_opacity))] = False  # never prune the last one
        keep &= ~prune
        if new or not bool(keep.all()):
            opt.surgery(keep, new or None)
        report = {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((~keep).sum()) - int(split.sum()),
                  "particles": len(model)}
        self.reset(len(model), dev)
        if self.reset_opacity_every and it % self.reset_opacity_every == 0:
            cap = math.log(self.reset_opacity_value / (1 - self.reset_opacity_value))
            model.logit_opacity.clamp_(max=cap)
        return report


__all__ = ["ParticleOptimizer", "make_optimizer", "DensifyConfig", "DensifyPrune"]
