"""Gaussian particles (paper Sec. 3.1): a Lagrangian particle extended with a 3D Gaussian.

Stored as raw (unconstrained) parameters, as optimisers want them; activations give the
renderer's inputs: scale = exp(log_scale), opacity = sigmoid(logit), rotation from a
quaternion of any norm, colour from SH coefficients (degree 0-3, 1 or 3 channels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .render.constants import SH_C0


@dataclass
class GaussianParticles:
    means: torch.Tensor          # (N, 3)
    log_scales: torch.Tensor     # (N, 3)
    quats: torch.Tensor          # (N, 4) w, x, y, z
    logit_opacity: torch.Tensor  # (N,)
    sh: torch.Tensor             # (N, (degree+1)^2, C)

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.logit_opacity)

    @property
    def sh_degree(self) -> int:
        return int(math.isqrt(self.sh.shape[1])) - 1

    @property
    def channels(self) -> int:
        return self.sh.shape[2]

    @classmethod
    def from_positions(cls, positions, radius: float, *, color=(0.5, 0.7, 1.0), opacity: float = 0.5,
                       sh_degree: int = 1, channels: int = 3, dtype=torch.float32, device=None):
        """Isotropic particles of std ``radius`` at ``positions`` with one colour and opacity."""
        p = torch.as_tensor(np.asarray(positions), dtype=dtype, device=device).reshape(-1, 3)
        n = p.shape[0]
        if not 0 < opacity < 1:
            raise ValueError(f"opacity must be in (0, 1), got {opacity}")
        if radius <= 0:
            raise ValueError(f"radius must be positive, got {radius}")
        col = torch.as_tensor(color, dtype=dtype, device=device).reshape(-1)[:channels]
        sh = torch.zeros(n, (sh_degree + 1) ** 2, channels, dtype=dtype, device=device)
        sh[:, 0, :] = (col - 0.5) / SH_C0  # colour = SH_C0 * sh0 + 0.5
        quats = torch.zeros(n, 4, dtype=dtype, device=device)
        quats[:, 0] = 1
        return cls(means=p.clone(), log_scales=torch.full((n, 3), math.log(radius), dtype=dtype, device=device),
                   quats=quats, logit_opacity=torch.full((n,), math.log(opacity / (1 - opacity)), dtype=dtype,
                                                         device=device), sh=sh)

    def render(self, camera, background=None, **kw):
        from .render import render

        return render(self.means, self.scales, self.quats, self.opacities, self.sh, camera, background, **kw)
