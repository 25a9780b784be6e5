"""Image quality metrics for renders against held-out photos (PSNR, SSIM), in torch.

Images are float tensors in [0, 1] (``data_range = 1``), channels last: (H, W, C) or (B, H, W, C).
Geometry metrics (chamfer, F-score) live with the geometry code.
"""
from __future__ import annotations

import torch
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


def ssim(
    pred: Tensor,
    target: Tensor,
    data_range: float = 1.0,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> Tensor:
    """Structural similarity (Wang et al. 2004) in the standard setting, by scikit-image: 11x11 Gaussian window
    (sigma 1.5), population statistics, ``C1 = (k1 L)^2``, ``C2 = (k2 L)^2``, the SSIM map averaged over the valid
    region, pixels and channels — ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
    use_sample_covariance=False, channel_axis=-1)``.

    pred, target: (H, W, C) or (B, H, W, C) in [0, data_range], H and W >= 11.
    Returns a 0-dim tensor (mean over the batch too).
    """
    from skimage.metrics import structural_similarity

    if pred.shape != target.shape:
        raise ValueError(f"pred and target must have the same shape, got {tuple(pred.shape)} and {tuple(target.shape)}")
    if pred.dim() not in (3, 4):
        raise ValueError(f"ssim expects (H, W, C) or (B, H, W, C) images, got {tuple(pred.shape)}")
    x = (pred if pred.dim() == 4 else pred[None]).detach().cpu().double().numpy()
    y = (target if target.dim() == 4 else target[None]).detach().cpu().double().numpy()
    win = 2 * int(3.5 * sigma + 0.5) + 1  # skimage's Gaussian window for this sigma (truncate 3.5)
    if min(x.shape[1:3]) < win:
        raise ValueError(f"ssim needs images of at least {win}x{win} pixels, got {tuple(x.shape[1:3])}")
    values = [
        structural_similarity(a, b, data_range=data_range, channel_axis=-1, gaussian_weights=True, sigma=sigma,
                              use_sample_covariance=False, K1=k1, K2=k2)
        for a, b in zip(x, y)
    ]
    return torch.tensor(float(sum(values) / len(values)), dtype=pred.dtype if pred.is_floating_point() else torch.float64)
