"""Positional encoding: layout, frequencies (2^k pi), dims and dtype/device handling."""
from __future__ import annotations

import math

import pytest
import torch

from recon.nerf.encoding import PositionalEncoding


def test_out_dim_matches_nerf_paper() -> None:
    assert PositionalEncoding(10).out_dim == 63  # positions
    assert PositionalEncoding(4).out_dim == 27  # directions
    assert PositionalEncoding(6, include_input=False, in_dim=2).out_dim == 24


def test_values_are_sin_cos_of_two_power_pi() -> None:
    enc = PositionalEncoding(3)
    x = torch.tensor([[0.1, -0.7, 0.25]], dtype=torch.float64)
    y = enc(x)
    assert y.shape == (1, 21) and y.dtype == torch.float64
    torch.testing.assert_close(y[0, :3], x[0])
    for k in range(3):
        for d in range(3):
            arg = (2**k) * math.pi * x[0, d].item()
            assert y[0, 3 + 3 * k + d].item() == pytest.approx(math.sin(arg))
            assert y[0, 12 + 3 * k + d].item() == pytest.approx(math.cos(arg))


def test_batch_shapes_and_lowest_band_period() -> None:
    enc = PositionalEncoding(2, include_input=False)
    x = torch.rand(4, 5, 3) * 2 - 1
    y = enc(x)
    assert y.shape == (4, 5, 12)
    # band 0 has period 2 (one period over [-1, 1])
    torch.testing.assert_close(enc(x + 2.0), y, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match=r"expects \(\.\.\., 3\)"):
        enc(torch.zeros(4, 2))


def test_buffer_not_in_state_dict() -> None:
    assert PositionalEncoding(4).state_dict() == {}
