"""Visual consistency (paper Eq. 11's L_rgb and L_d-ssim, as in 3DGS, Kerbl et al. 2023): the
rendered images against the training images, each term the mean over the step's images, one batch
per image size (a step's op count does not grow with its images).

Coarse to fine (not in the paper): in phase 2 the L1 term compares images blurred with a Gaussian
of ``loss.blur_start`` x width that shrinks to none as the time window widens (``Step.blur``):
a particle then feels fluid beyond its own footprint (large motions)."""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F

from .base import Term


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_rgb: mean absolute error (of a batch of same-size images: the mean of their L_rgb)."""
    return (pred - target).abs().mean()


@lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float, dtype, device_str: str) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).to(dtype=dtype, device=torch.device(device_str))


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (B, C, H, W), 'valid' borders (as 3DGS's SSIM with padding)."""
    c = x.shape[1]
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c, padding=(0, k // 2))
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c, padding=(k // 2, 0))


def _nchw(img: torch.Tensor) -> torch.Tensor:
    """(H, W, C) or a batch (B, H, W, C) -> (B, C, H, W)."""
    return img.permute(2, 0, 1)[None] if img.dim() == 3 else img.permute(0, 3, 1, 2)


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W, C) image, or a batch (B, H, W, C), blurred with a Gaussian of ``sigma`` pixels
    (separable, zero padding)."""
    size = 2 * int(math.ceil(3 * sigma)) + 1
    x = _nchw(img)
    g = _gauss_1d(size, float(sigma), x.dtype, str(x.device))
    y = _blur(x, g).permute(0, 2, 3, 1)
    return y[0] if img.dim() == 3 else y


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) of (H, W, C) images in [0, 1] with an 11x11 Gaussian window
    (sigma 1.5), zero padding as in 3DGS. Separable filtering: 2 x 11 taps per pixel, not 121.
    A batch (B, H, W, C) of same-size images gives the mean of their SSIMs."""
    x, y = _nchw(pred), _nchw(target)
    g = _gauss_1d(window, sigma, x.dtype, str(x.device))
    both = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g)
    c = x.shape[1]
    mu_x, mu_y, xx, yy, xy = both.split(c, 1)
    sx, sy, sxy = xx - mu_x ** 2, yy - mu_y ** 2, xy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sx + sy + c2))
    return s.mean()


def d_ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_d-ssim = 1 - SSIM."""
    return 1.0 - ssim(pred, target)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1]; inf for identical images."""
    mse = float(((pred.detach() - target.detach()) ** 2).mean())
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


class ImageTerm(Term):
    def step(self, ctx, s, w):
        loss = 0.0
        for width, pred, target in s.batches:
            li = 0.0
            if w["rgb"] > 0:
                sigma = s.blur * width
                if sigma >= 0.5:
                    li = li + w["rgb"] * l1(blur(pred, sigma), blur(target, sigma))
                else:
                    li = li + w["rgb"] * l1(pred, target)
            if w["ssim"] > 0:
                li = li + w["ssim"] * d_ssim(pred, target)
            loss = loss + li * (pred.shape[0] / s.n_images)
        return loss


# lambda_r and lambda_s of Table 1
IMAGE = ImageTerm("image", (("rgb", 0.2), ("ssim", 0.1)), per="step")
