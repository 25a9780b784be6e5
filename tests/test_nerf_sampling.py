"""Stratified and inverse-CDF sampling: ranges, order, determinism, and the degenerate weight cases."""
from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from recon.nerf.sampling import sample_pdf, stratified


def test_stratified_midpoints_and_jitter_stay_in_their_bins() -> None:
    near, far = torch.tensor([2.0, 0.0]), torch.tensor([6.0, 1.0])
    mid = stratified(near, far, 4, jitter=False)
    torch.testing.assert_close(mid, torch.tensor([[2.5, 3.5, 4.5, 5.5], [0.125, 0.375, 0.625, 0.875]]))
    g = torch.Generator().manual_seed(0)
    t = stratified(near.repeat(500), far.repeat(500), 4, jitter=True, generator=g)
    width = ((far - near) / 4).repeat(500)[:, None]
    lo = near.repeat(500)[:, None] + torch.arange(4) * width
    assert torch.all(t >= lo) and torch.all(t < lo + width)
    # jitter is uniform within the bin: mean offset ~ 0.5 of the width
    assert ((t - lo) / width).mean().item() == pytest.approx(0.5, abs=0.02)


def test_stratified_is_reproducible_with_a_generator_and_keeps_dtype() -> None:
    near, far = torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    a = stratified(near, far, 5, True, torch.Generator().manual_seed(7))
    b = stratified(near, far, 5, True, torch.Generator().manual_seed(7))
    assert a.dtype == torch.float64 and torch.equal(a, b)
    # a zero-length interval gives finite, identical samples
    z = stratified(torch.ones(2), torch.ones(2), 3, jitter=True)
    assert torch.all(z == 1.0)


def test_pdf_uniform_weights_reproduce_uniform_quantiles() -> None:
    bins = torch.linspace(2.0, 6.0, 9).expand(3, 9)
    t = sample_pdf(bins, torch.ones(3, 8), 4, deterministic=True)
    torch.testing.assert_close(t, torch.tensor([2.5, 3.5, 4.5, 5.5]).expand(3, 4))


def test_pdf_closed_form_for_two_bins() -> None:
    # mass 1/4 on [0, 1], 3/4 on [1, 3]: quantile q maps to 4q on the first bin, 1 + 2(q - 1/4)/(3/4) after
    bins = torch.tensor([[0.0, 1.0, 3.0]], dtype=torch.float64)
    w = torch.tensor([[0.25, 0.75]], dtype=torch.float64)
    t = sample_pdf(bins, w, 4, deterministic=True)
    q = (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    expected = torch.where(q < 0.25, 4 * q, 1 + 2 * (q - 0.25) / 0.75)
    torch.testing.assert_close(t[0], expected, rtol=0, atol=1e-4)  # the 1e-5 floor shifts it slightly


def test_pdf_one_hot_and_all_zero_weights_are_finite() -> None:
    bins = torch.linspace(0.0, 1.0, 11).expand(2, 11).contiguous()
    w = torch.zeros(2, 10)
    w[0, 3] = 1.0
    t = sample_pdf(bins, w, 64, deterministic=False, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(t).all()
    assert ((t[0] >= 0.3) & (t[0] <= 0.4)).float().mean() > 0.99
    # all-zero weights: uniform over the whole ray
    assert t[1].min() < 0.05 and t[1].max() > 0.95
    t_nan = sample_pdf(bins, torch.full((2, 10), float("nan")), 8, deterministic=True)
    assert torch.isfinite(t_nan).all()


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 12), n_new=st.integers(1, 40), seed=st.integers(0, 2**31 - 1), sparse=st.booleans())
def test_pdf_samples_sorted_and_within_range(n: int, n_new: int, seed: int, sparse: bool) -> None:
    g = torch.Generator().manual_seed(seed)
    bins = torch.sort(torch.rand(5, n + 1, generator=g) * 4 + 2, dim=-1).values
    w = torch.rand(5, n, generator=g)
    if sparse:
        w = w * (torch.rand(5, n, generator=g) < 0.2)
    t = sample_pdf(bins, w, n_new, deterministic=False, generator=g)
    assert t.shape == (5, n_new)
    assert torch.all(t >= bins[:, :1]) and torch.all(t <= bins[:, -1:])
    assert torch.all(t[:, 1:] >= t[:, :-1])


def test_pdf_follows_the_weights_statistically() -> None:
    bins = torch.linspace(0.0, 4.0, 5).expand(1, 5)
    w = torch.tensor([[1.0, 0.0, 3.0, 0.0]])
    t = sample_pdf(bins.expand(2000, 5), w.expand(2000, 4), 8, deterministic=False, generator=torch.Generator().manual_seed(3))
    frac_bin2 = ((t >= 2) & (t < 3)).float().mean().item()
    assert frac_bin2 == pytest.approx(0.75, abs=0.01)


def test_pdf_bad_shapes_raise() -> None:
    with pytest.raises(ValueError, match=r"bins must be \(N, n\+1\)"):
        sample_pdf(torch.zeros(2, 4), torch.zeros(2, 4), 3, True)
