"""Volume rendering against closed forms, at the numeric extremes, and packed == dense."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from recon.nerf.render import (
    accumulate_packed,
    alpha_from_density,
    composite,
    render_dense,
    render_packed,
    render_weights,
    render_weights_packed,
)


def _slab(sigma: float, near: float, far: float, n: int, dtype=torch.float32):
    """One ray with n samples evenly from near, constant density, ending at far."""
    t = torch.linspace(near, far, n + 1, dtype=dtype)[:-1][None]
    return torch.full_like(t, sigma), t, torch.tensor([far], dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.01, 0.3, 2.0, 50.0])
def test_constant_slab_follows_beer_lambert(sigma: float, dtype: torch.dtype) -> None:
    s, t, far = _slab(sigma, 2.0, 4.5, 37, dtype)
    out = render_dense(s, torch.rand(1, 37, 3, dtype=dtype), t, far, torch.zeros(3, dtype=dtype))
    expected = 1.0 - math.exp(-sigma * 2.5)
    assert out["opacity"].dtype == dtype
    assert out["opacity"].item() == pytest.approx(expected, rel=1e-5, abs=1e-6)
    # the transmittance at sample i is exp(-sigma * (t_i - near)) exactly
    _, trans = render_weights(s, t, far - t[:, -1])
    torch.testing.assert_close(trans, torch.exp(-sigma * (t - 2.0)), rtol=1e-5, atol=1e-6)


def test_empty_ray_shows_background_at_far() -> None:
    t = torch.linspace(1.0, 3.0, 8).expand(2, 8)
    bg = torch.tensor([[0.2, 0.4, 0.6], [1.0, 1.0, 1.0]])
    out = render_dense(torch.zeros(2, 8), torch.rand(2, 8, 3), t, torch.full((2,), 3.5), bg)
    torch.testing.assert_close(out["rgb"], bg)
    torch.testing.assert_close(out["depth"], torch.full((2,), 3.5))
    torch.testing.assert_close(out["median_depth"], torch.full((2,), 3.5))
    assert torch.all(out["opacity"] == 0)


def test_single_opaque_surface_gives_its_color_and_depth() -> None:
    t = torch.linspace(1.0, 5.0, 9)[None]
    sigma = torch.zeros(1, 9)
    sigma[0, 5] = 1e6
    rgb = torch.rand(1, 9, 3)
    out = render_dense(sigma, rgb, t, torch.tensor([5.5]), torch.ones(3))
    torch.testing.assert_close(out["rgb"], rgb[:, 5])
    assert out["depth"].item() == pytest.approx(t[0, 5].item())
    assert out["median_depth"].item() == pytest.approx(t[0, 5].item())
    assert out["opacity"].item() == pytest.approx(1.0)


def test_alpha_keeps_tiny_densities() -> None:
    # 1 - exp(-1e-12) rounds to 0 in float32; -expm1 does not
    a = alpha_from_density(torch.tensor([1e-12]), torch.tensor([1.0]))
    assert a.item() == pytest.approx(1e-12, rel=1e-6)
    assert alpha_from_density(torch.tensor([math.inf]), torch.tensor([0.1])).item() == 1.0


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 4),
    s=st.integers(1, 16),
    scale=st.sampled_from([1e-6, 1e-2, 1.0, 1e2, 1e6]),
    seed=st.integers(0, 2**31 - 1),
)
def test_weights_are_in_unit_interval_and_sum_at_most_one(n: int, s: int, scale: float, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    sigma = torch.rand(n, s, generator=g) * scale
    t = torch.sort(torch.rand(n, s, generator=g) * 4 + 2, dim=-1).values
    w, trans = render_weights(sigma, t, far_delta=torch.rand(n, generator=g))
    assert torch.all(w >= 0) and torch.all(w <= 1)
    assert torch.all(w.sum(-1) <= 1 + 1e-6)
    assert torch.all((trans > 0) | (trans == 0)) and torch.all(trans <= 1)
    assert torch.all(trans[:, 0] == 1)


@pytest.mark.parametrize("density", [0.0, 1e-12, 1e6, 1e12, math.inf])
@pytest.mark.parametrize("spacing", [1e-9, 1.0, 1e3])
@pytest.mark.parametrize("samples", [1, 5])
def test_extremes_are_finite_with_finite_gradients(density: float, spacing: float, samples: int) -> None:
    sigma = torch.full((3, samples), density, requires_grad=True)
    rgb = torch.rand(3, samples, 3, requires_grad=True)
    t = (2.0 + spacing * torch.arange(samples, dtype=torch.float32)).expand(3, samples).contiguous()
    far = t[:, -1] + spacing
    out = render_dense(sigma, rgb, t, far, torch.ones(3))
    for k, v in out.items():
        assert torch.isfinite(v).all(), k
    assert torch.all(out["opacity"] <= 1) and torch.all(out["opacity"] >= 0)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(rgb.grad).all()


def test_nan_density_propagates() -> None:
    sigma = torch.tensor([[1.0, math.nan, 1.0]])
    out = render_dense(sigma, torch.rand(1, 3, 3), torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([4.0]), torch.ones(3))
    assert torch.isnan(out["rgb"]).all()


def test_gradcheck_dense_float64() -> None:
    g = torch.Generator().manual_seed(0)
    sigma = (torch.rand(3, 5, generator=g, dtype=torch.float64) * 2).requires_grad_()
    rgb = torch.rand(3, 5, 3, generator=g, dtype=torch.float64).requires_grad_()
    t = torch.sort(torch.rand(3, 5, generator=g, dtype=torch.float64) + 1, dim=-1).values.requires_grad_()
    far = torch.full((3,), 2.5, dtype=torch.float64)
    bg = torch.rand(3, dtype=torch.float64)

    def f(sigma, rgb, t):
        out = render_dense(sigma, rgb, t, far, bg)
        return out["rgb"], out["depth"], out["opacity"]

    assert torch.autograd.gradcheck(f, (sigma, rgb, t))


def test_gradcheck_packed_float64() -> None:
    g = torch.Generator().manual_seed(1)
    sigma = (torch.rand(7, generator=g, dtype=torch.float64) * 3).requires_grad_()
    rgb = torch.rand(7, 3, generator=g, dtype=torch.float64).requires_grad_()
    delta = (torch.rand(7, generator=g, dtype=torch.float64) * 0.5).requires_grad_()
    t_mid = torch.rand(7, generator=g, dtype=torch.float64)
    idx = torch.tensor([0, 0, 0, 2, 2, 3, 3])

    def f(sigma, rgb, delta):
        out = render_packed(sigma, rgb, t_mid, delta, idx, 4, torch.ones(3, dtype=torch.float64))
        return out["rgb"], out["opacity"]

    assert torch.autograd.gradcheck(f, (sigma, rgb, delta))


def test_packed_equals_dense_on_ragged_rays() -> None:
    g = torch.Generator().manual_seed(2)
    counts = [5, 0, 1, 12, 3, 7]
    n = len(counts)
    sig_l, rgb_l, t_l, idx_l = [], [], [], []
    far = torch.rand(n, generator=g) + 6.0
    bg = torch.rand(n, 3, generator=g)
    dense = []
    for r, c in enumerate(counts):
        t = torch.sort(torch.rand(1, c, generator=g) * 4 + 2, dim=-1).values
        sig = torch.rand(1, c, generator=g) * 3
        rgb = torch.rand(1, c, 3, generator=g)
        if c:
            dense.append(render_dense(sig, rgb, t, far[r : r + 1], bg[r : r + 1]))
        else:
            dense.append({"rgb": bg[r : r + 1], "depth": far[r : r + 1], "opacity": torch.zeros(1)})
        sig_l.append(sig[0]), rgb_l.append(rgb[0]), t_l.append(t[0]), idx_l.append(torch.full((c,), r))
    t_all = torch.cat(t_l)
    delta = torch.cat([torch.cat([t[1:] - t[:-1], far[r : r + 1] - t[-1:]]) for r, t in enumerate(t_l) if len(t)])
    out = render_packed(torch.cat(sig_l), torch.cat(rgb_l), t_all, delta, torch.cat(idx_l), n, bg, t_far=far)
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(out[k], torch.cat([d[k] for d in dense]), msg=k)
    w_dense = torch.cat([d["weights"][0] for d in dense if "weights" in d])
    torch.testing.assert_close(out["weights"], w_dense)


def test_packed_transmittance_stays_exact_after_many_opaque_rays() -> None:
    # 20000 opaque rays before a faint one: a float32 global cumsum would have ~1 unit of error here
    n_opaque = 20000
    sigma = torch.cat([torch.full((2 * n_opaque,), 1e4), torch.full((4,), 0.1)])
    delta = torch.full_like(sigma, 0.5)
    idx = torch.cat([torch.arange(n_opaque).repeat_interleave(2), torch.full((4,), n_opaque)])
    w, trans = render_weights_packed(sigma, delta, idx, n_opaque + 1)
    expected = torch.exp(-0.05 * torch.arange(4.0))
    torch.testing.assert_close(trans[-4:], expected)
    torch.testing.assert_close(trans[:2 * n_opaque:2], torch.ones(n_opaque))


def test_accumulate_packed_shapes() -> None:
    w = torch.tensor([0.5, 0.25, 1.0])
    idx = torch.tensor([0, 0, 2])
    torch.testing.assert_close(accumulate_packed(w, None, idx, 3), torch.tensor([0.75, 0.0, 1.0]))
    v = torch.tensor([[1.0, 2.0], [4.0, 0.0], [3.0, 3.0]])
    torch.testing.assert_close(accumulate_packed(w, v, idx, 3), torch.tensor([[1.5, 1.0], [0.0, 0.0], [3.0, 3.0]]))
    torch.testing.assert_close(composite(w[None], v[None]), torch.tensor([[4.5, 4.0]]))


def test_bad_inputs_raise_clear_errors() -> None:
    with pytest.raises(ValueError, match=r"rgb must have shape \(2, 4, 3\)"):
        render_dense(torch.zeros(2, 4), torch.zeros(2, 4), torch.zeros(2, 4), torch.zeros(2), torch.ones(3))
    with pytest.raises(ValueError, match="sorted ascending"):
        render_weights_packed(torch.ones(3), torch.ones(3), torch.tensor([1, 0, 1]), 2)
    with pytest.raises(ValueError, match=r"in \[0, 2\)"):
        render_weights_packed(torch.ones(3), torch.ones(3), torch.tensor([0, 1, 2]), 2)
    with pytest.raises(ValueError, match="torch.long"):
        render_weights_packed(torch.ones(2), torch.ones(2), torch.tensor([0, 1], dtype=torch.int32), 2)


def test_weights_sum_to_at_most_one_after_an_opaque_sample() -> None:
    # hypothesis found it: a thin sample, then a nearly opaque one (tau ~ 260); cumsum(tau) - tau rounded the first
    # tau away in float32 and the weights summed to 1 + 4e-6
    sigma = torch.tensor([[83.2126, 83.3703, 38.7942]])
    t = torch.tensor([[2.3715, 2.3862, 5.5098]])
    w, _ = render_weights(sigma, t, far_delta=torch.tensor([0.5]))
    assert w.sum().item() <= 1 + 1e-6
