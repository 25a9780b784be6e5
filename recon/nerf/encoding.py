"""Positional (Fourier feature) encoding of coordinates, NeRF eq. 4."""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

__all__ = ["PositionalEncoding"]


class PositionalEncoding(nn.Module):
    """``gamma(p) = (p, sin(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^0 pi p), ..., cos(2^(L-1) pi p))``.

    Frequencies are ``2^k * pi`` for ``k = 0 .. n_freqs-1`` (the paper's form, which expects inputs
    in [-1, 1]: the lowest band then has one period over the box). The official code drops the
    pi; with the pi the same ``n_freqs`` reaches a pi times finer scale.

    Layout of the output's last axis: ``[p (D, if include_input), sin (n_freqs * D), cos (n_freqs * D)]``
    with the sin/cos blocks ordered frequency-major (all D coordinates of band 0, then band 1, ...).

    Args:
        n_freqs: number of frequency bands L (0 allowed: identity when include_input).
        include_input: prepend the raw coordinates.
        in_dim: D, the size of the input's last axis (3 for positions and directions).
    """

    def __init__(self, n_freqs: int, include_input: bool = True, in_dim: int = 3) -> None:
        super().__init__()
        if n_freqs < 0 or (n_freqs == 0 and not include_input):
            raise ValueError(f"n_freqs must be >= 0 (and > 0 without include_input), got {n_freqs}")
        self.n_freqs = n_freqs
        self.include_input = include_input
        self.in_dim = in_dim
        self.out_dim = in_dim * (int(include_input) + 2 * n_freqs)
        # powers of two are exact in any float dtype; pi is applied in the input's dtype in forward
        self.register_buffer("pow2", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """x: (..., D) -> (..., out_dim), in x's dtype."""
        if x.shape[-1] != self.in_dim:
            raise ValueError(f"PositionalEncoding expects (..., {self.in_dim}) input, got {tuple(x.shape)}")
        parts = [x] if self.include_input else []
        if self.n_freqs:
            xb = (x[..., None, :] * self.pow2.to(x.dtype)[:, None] * math.pi).flatten(-2)  # (..., L * D)
            parts += [torch.sin(xb), torch.cos(xb)]
        return torch.cat(parts, dim=-1)

    def extra_repr(self) -> str:
        return f"n_freqs={self.n_freqs}, include_input={self.include_input}, in_dim={self.in_dim}, out_dim={self.out_dim}"
