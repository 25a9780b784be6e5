"""Where to put samples along rays: stratified bins, and inverse-CDF resampling (NeRF's hierarchical sampling)."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["sample_pdf", "stratified"]


def stratified(
    near: Tensor, far: Tensor, n: int, jitter: bool, generator: torch.Generator | None = None
) -> Tensor:
    """``n`` samples per ray, one in each of ``n`` equal bins of ``[near, far]``.

    Args:
        near, far: (N,) ray interval (world units); ``far == near`` gives n identical samples.
        n: samples per ray (>= 1).
        jitter: True: a uniform random position inside each bin (training, NeRF eq. 2);
            False: the bin midpoints (deterministic, for evaluation).
        generator: RNG for the jitter (on the tensors' device); None uses torch's global RNG.

    Returns:
        t: (N, n) sorted ascending, ``near <= t < far``; same device and dtype as ``near``.
    """
    if near.dim() != 1 or far.shape != near.shape:
        raise ValueError(f"near and far must both be (N,), got {tuple(near.shape)} and {tuple(far.shape)}")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    k = torch.arange(n, device=near.device, dtype=near.dtype)
    if jitter:
        u = torch.rand((near.shape[0], n), generator=generator, device=near.device, dtype=near.dtype)
    else:
        u = torch.full((1, n), 0.5, device=near.device, dtype=near.dtype)
    width = (far - near)[:, None] / n
    return near[:, None] + (k + u) * width


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    n_new: int,
    deterministic: bool,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``n_new`` distances from the piecewise-constant density given by ``weights`` over ``bins``.

    Args:
        bins: (N, n+1) bin edges along each ray, non-decreasing (world units).
        weights: (N, n) non-negative mass of each bin (e.g. the coarse compositing weights). No
            gradient flows back through sampling (weights are detached). A small floor (1e-5 per
            bin, as in NeRF) keeps all-zero rays uniform and the CDF strictly increasing, so
            all-zero and one-hot weights both give finite samples.
        n_new: samples to draw per ray.
        deterministic: True: quantiles at ``(k + 0.5) / n_new`` (evaluation); False: one uniform
            draw in each of ``n_new`` equal strata of [0, 1) (stratified, lower variance than iid).
        generator: RNG for the random draws; None uses torch's global RNG.

    Returns:
        t: (N, n_new) sorted ascending, inside ``[bins[:, 0], bins[:, -1]]``.
    """
    if bins.dim() != 2 or weights.dim() != 2 or bins.shape != (weights.shape[0], weights.shape[1] + 1):
        raise ValueError(
            f"bins must be (N, n+1) and weights (N, n); got {tuple(bins.shape)} and {tuple(weights.shape)}"
        )
    n_rays = bins.shape[0]
    w = weights.detach().clamp_min(0.0).nan_to_num(0.0) + 1e-5
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cumsum(pdf, dim=-1).clamp_max(1.0)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf[:, :-1], torch.ones_like(cdf[:, :1])], dim=-1)
    k = torch.arange(n_new, device=bins.device, dtype=bins.dtype)
    if deterministic:
        u = ((k + 0.5) / n_new).expand(n_rays, n_new)
    else:
        r = torch.rand((n_rays, n_new), generator=generator, device=bins.device, dtype=bins.dtype)
        u = (k + r) / n_new
    u = u.contiguous()
    above = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(1, cdf.shape[-1] - 1)
    below = above - 1
    cdf_lo, cdf_hi = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_lo, bin_hi = bins.detach().gather(-1, below), bins.detach().gather(-1, above)
    denom = cdf_hi - cdf_lo
    frac = torch.where(denom > 0, (u - cdf_lo) / denom.clamp_min(1e-12), torch.zeros_like(u)).clamp(0.0, 1.0)
    return bin_lo + frac * (bin_hi - bin_lo)
