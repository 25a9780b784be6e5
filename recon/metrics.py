"""Image quality metrics for renders against held-out photos (PSNR, SSIM), in torch.

Images are float tensors in [0, 1] (``data_range = 1``), channels last: (H, W, C) or (B, H, W, C).
Geometry metrics (chamfer, F-score) live with the geometry code.
"""
from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["mse_to_psnr", "psnr", "ssim"]


def mse_to_psnr(mse: Tensor | float, data_range: float = 1.0) -> Tensor:
    """PSNR in dB from a mean squared error: ``10 log10(data_range^2 / mse)`` (inf for mse = 0)."""
    mse = torch.as_tensor(mse, dtype=torch.float64 if not isinstance(mse, Tensor) else None)
    return 10.0 * torch.log10(data_range**2 / mse)


def psnr(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB over all pixels and channels (a 0-dim tensor).

    pred, target: same shape, values in [0, data_range]. The mean squared error is taken in
    float64 so that near-identical images do not round to inf.
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {tuple(pred.shape)} and {tuple(target.shape)}")
    mse = torch.mean((pred.double() - target.double()) ** 2)
    return mse_to_psnr(mse, data_range)


def _gaussian_window(size: int, sigma: float, like: Tensor) -> Tensor:
    x = torch.arange(size, device=like.device, dtype=like.dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(
    pred: Tensor,
    target: Tensor,
    data_range: float = 1.0,
    win_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> Tensor:
    """Structural similarity (Wang et al. 2004), the standard setting: 11x11 Gaussian window, sigma 1.5.

    Local means/variances/covariance use the Gaussian window over the VALID region only (no
    padding), population (not sample) statistics, ``C1 = (k1 L)^2``, ``C2 = (k2 L)^2``; the SSIM
    map is averaged over pixels and channels. This equals
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)``.

    pred, target: (H, W, C) or (B, H, W, C) in [0, data_range], H and W >= win_size.
    Returns a 0-dim tensor (mean over the batch too).
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {tuple(pred.shape)} and {tuple(target.shape)}")
    if pred.dim() not in (3, 4):
        raise ValueError(f"ssim expects (H, W, C) or (B, H, W, C) images, got {tuple(pred.shape)}")
    x = (pred if pred.dim() == 4 else pred[None]).permute(0, 3, 1, 2).double()
    y = (target if target.dim() == 4 else target[None]).permute(0, 3, 1, 2).double()
    if min(x.shape[-2:]) < win_size:
        raise ValueError(f"ssim needs images of at least {win_size}x{win_size} pixels, got {tuple(x.shape[-2:])}")
    c = x.shape[1]
    g = _gaussian_window(win_size, sigma, x)
    wy = g.view(1, 1, -1, 1).expand(c, 1, win_size, 1)
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, win_size)

    def blur(z: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(z, wy, groups=c), wx, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s.mean().to(pred.dtype if pred.is_floating_point() else torch.float64)
