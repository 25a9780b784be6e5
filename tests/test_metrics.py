"""PSNR and SSIM against closed forms, a written-out SSIM and scikit-image."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from recon.evaluation.metrics import mse_to_psnr, psnr, ssim


def test_psnr_closed_form() -> None:
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert psnr(a, b).item() == pytest.approx(20.0)  # mse 0.01 -> 20 dB
    assert psnr(a, a).item() == math.inf
    assert mse_to_psnr(1e-3).item() == pytest.approx(30.0)
    assert psnr(a * 255, b * 255, data_range=255).item() == pytest.approx(20.0)


def _pair(seed: int, shape=(37, 41, 3)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # smooth structure + noise, so that SSIM is far from 0 and 1
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    base = 0.5 + 0.4 * np.sin(xx[..., None] / 5.0 + np.arange(shape[2])) * np.cos(yy[..., None] / 7.0)
    a = np.clip(base + rng.normal(0, 0.05, shape), 0, 1)
    b = np.clip(base * 0.9 + 0.05 + rng.normal(0, 0.1, shape), 0, 1)
    return a, b


def _reference_ssim(a: np.ndarray, b: np.ndarray, win_size: int = 11, sigma: float = 1.5) -> float:
    """SSIM written out from Wang et al. 2004 (Gaussian window over the valid region, population statistics):
    an independent check that `ssim` calls scikit-image with the standard settings."""
    import torch.nn.functional as F

    x = torch.from_numpy(a)[None].permute(0, 3, 1, 2).double()
    y = torch.from_numpy(b)[None].permute(0, 3, 1, 2).double()
    c = x.shape[1]
    t = torch.arange(win_size, dtype=torch.float64) - (win_size - 1) / 2
    g = torch.exp(-(t**2) / (2 * sigma**2))
    g /= g.sum()
    wy, wx = g.view(1, 1, -1, 1).expand(c, 1, win_size, 1), g.view(1, 1, 1, -1).expand(c, 1, 1, win_size)

    def blur(z: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(z, wy, groups=c), wx, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2, blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return float(s.mean())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_skimage(seed: int) -> None:
    a, b = _pair(seed)
    ref = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    ours = ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    assert 0.2 < ref < 0.95
    assert ours.item() == pytest.approx(ref, abs=1e-5)
    assert ours.item() == pytest.approx(_reference_ssim(a, b), abs=1e-5)


@pytest.mark.parametrize("a, b", [(0.2, 0.6), (0.5, 0.5), (0.9, 0.1)])
def test_ssim_of_flat_images_is_the_luminance_term(a: float, b: float) -> None:
    """No structure: variances and covariance vanish, SSIM = (2ab + C1) / (a² + b² + C1)."""
    c1 = 0.01**2
    got = ssim(torch.full((16, 16, 3), a), torch.full((16, 16, 3), b)).item()
    assert got == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), abs=1e-6)


def test_ssim_identity_batch_and_errors() -> None:
    a, b = _pair(3, (20, 24, 3))
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    assert ssim(ta, ta).item() == pytest.approx(1.0)
    batch = ssim(torch.stack([ta, ta]), torch.stack([tb, tb]))
    assert batch.item() == pytest.approx(ssim(ta, tb).item())
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 8, 3))
    with pytest.raises(ValueError, match="same shape"):
        psnr(torch.zeros(2, 2, 3), torch.zeros(2, 3, 3))
