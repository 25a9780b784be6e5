"""NeRF numerics at the extremes not covered by tests/test_nerf_*.py: contraction of huge and infinite points,
encodings over the whole contracted box, grids fed NaN/inf/out-of-box points, hierarchical sampling with
degenerate weights and bins, rendering with near ~ 0 and far >> scene, float64 gradchecks at the extremes,
and bf16 autocast keeping the compositing in float32."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from recon.nerf.classic import ClassicModel
from recon.nerf.contraction import contract, uncontract
from recon.nerf.encoding import PositionalEncoding
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.grid import DenseGrid, HashGrid, VMGrid, axis_cells
from recon.nerf.render import render_dense, render_packed
from recon.nerf.sampling import sample_pdf, stratified

DTYPES = [torch.float32, torch.float64]


# ----------------------------------------------------------------------------------------- contraction
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("value", [1e12, 1e30, "max", math.inf, -math.inf])
def test_contraction_of_huge_and_infinite_points_lands_on_the_outer_face(value, dtype: torch.dtype) -> None:
    v = torch.finfo(dtype).max if value == "max" else value
    x = torch.tensor([[v, 0.5, -0.25], [0.5, v, v]], dtype=dtype)
    y = contract(x)
    assert torch.isfinite(y).all()
    sign = math.copysign(1.0, v)
    # ||y||_inf = 2 - 1/||x||_inf -> 2; the other coordinates scale by (2 - 1/n)/n -> 0
    assert y[0, 0].item() == pytest.approx(2.0 * sign, abs=1e-6) and abs(y[0, 1].item()) < 1e-6
    assert y[1, 1].item() == pytest.approx(2.0 * sign, abs=1e-6) and y[1, 2].item() == pytest.approx(2.0 * sign, abs=1e-6)
    assert torch.isnan(contract(torch.tensor([[math.nan, 0.0, 0.0]], dtype=dtype))).all(-1).any()


@given(
    direction=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda d: max(map(abs, d)) > 1e-3),
    log_norm=st.floats(-3, 37),
)
def test_contraction_is_finite_bounded_and_inverted_up_to_float_precision(direction, log_norm: float) -> None:
    d = torch.tensor(direction, dtype=torch.float64)
    x = (d / d.abs().max() * 10.0**log_norm)[None]
    y = contract(x)
    m = y.abs().max().item()
    assert torch.isfinite(y).all() and m <= 2.0
    n = 10.0**log_norm
    assert m == pytest.approx(n if n <= 1 else 2.0 - 1.0 / n, rel=1e-9)
    if log_norm < 12:  # beyond that 2 - 1/|x| rounds to 2 and the inverse is clamped: nothing to recover
        torch.testing.assert_close(uncontract(y), x, rtol=1e-15 * max(1.0, n) ** 2, atol=1e-12)


# ----------------------------------------------------------------------------------------- encodings and grids
@pytest.mark.parametrize("n_freqs", [4, 10])
def test_positional_encoding_over_the_contracted_box_is_accurate_in_float32(n_freqs: int) -> None:
    # |x| <= 2 after contraction: the highest band's argument is 2^(L-1) pi 2 (~3.2e3 for L = 10), where a
    # float32 ulp is ~2.4e-4, so sin/cos agree with float64 to a few 1e-4 (not worse: no large-argument blowup)
    x64 = torch.linspace(-2.0, 2.0, 4001, dtype=torch.float64)[:, None].expand(-1, 3).contiguous()
    pe = PositionalEncoding(n_freqs)
    e32, e64 = pe(x64.float()), pe(x64)
    assert e32.dtype == torch.float32 and torch.isfinite(e32).all()
    bound = 4 * 2.0 ** (n_freqs - 1) * math.pi * 2 * torch.finfo(torch.float32).eps
    assert (e32.double() - e64).abs().max().item() <= bound
    s, c = e32[:, 3 : 3 + 3 * n_freqs], e32[:, 3 + 3 * n_freqs :]
    torch.testing.assert_close(s * s + c * c, torch.ones_like(s), rtol=0, atol=1e-6)


def _grids() -> list[torch.nn.Module]:
    torch.manual_seed(0)
    return [DenseGrid(9, 2, init_std=1.0), VMGrid(9, 2, init_std=1.0), HashGrid(levels=4, log2_table=8, base_res=4, max_res=64, init_scale=1.0)]


@pytest.mark.parametrize("grid", _grids(), ids=["dense", "vm", "hash"])
def test_grids_at_faces_corners_and_beyond_never_read_out_of_range(grid: torch.nn.Module) -> None:
    corners = torch.tensor([[i, j, k] for i in (0.0, 1.0) for j in (0.0, 1.0) for k in (0.0, 1.0)])
    eps = torch.finfo(torch.float32).eps
    beyond = torch.tensor([[1 + eps, -eps, 0.5], [1e30, -1e30, 0.5], [math.inf, -math.inf, 0.5], [1 - eps / 2, 1.0, eps]])
    x = torch.cat([corners, beyond])
    out = grid(x)
    assert torch.isfinite(out).all()
    # outside the box reads the clamped face value exactly
    torch.testing.assert_close(out[8], grid(torch.tensor([[1.0, 0.0, 0.5]]))[0])
    torch.testing.assert_close(out[10], grid(torch.tensor([[1.0, 0.0, 0.5]]))[0])


@pytest.mark.parametrize("grid", _grids(), ids=["dense", "vm", "hash"])
def test_grid_lookup_of_nan_gives_nan_not_an_index_error(grid: torch.nn.Module) -> None:
    # regression: NaN positions became int64-min cell indices (IndexError from the gather, or an
    # out-of-range read); now the NaN propagates so the trainer's NaN guard names the step
    out = grid(torch.tensor([[math.nan, 0.5, 0.5], [0.25, 0.5, 0.75]]))
    assert torch.isnan(out[0]).any()
    assert torch.isfinite(out[1]).all()
    i0, _ = axis_cells(torch.tensor([[math.nan, 0.5, 1.0]]), 16)
    assert int(i0.min()) >= 0 and int(i0.max()) <= 14


# ----------------------------------------------------------------------------------------- hierarchical sampling
weight_values = st.sampled_from([0.0, 1e-30, 1e-6, 1.0, 1e6, 1e30, math.inf, math.nan])


@given(
    w=st.lists(weight_values, min_size=1, max_size=10),
    widths=st.lists(st.sampled_from([0.0, 1e-9, 1e-3, 1.0, 1e3]), min_size=10, max_size=10),
    n_new=st.integers(1, 33),
    deterministic=st.booleans(),
    double=st.booleans(),
)
def test_inverse_cdf_is_nan_free_sorted_and_in_range(w, widths, n_new: int, deterministic: bool, double: bool) -> None:
    dtype = torch.float64 if double else torch.float32
    weights = torch.tensor([w], dtype=dtype)
    bins = 2.0 + torch.cumsum(torch.tensor([[0.0] + widths[: len(w)]], dtype=dtype), dim=-1)
    t = sample_pdf(bins, weights, n_new, deterministic, generator=torch.Generator().manual_seed(0))
    assert t.dtype == dtype and torch.isfinite(t).all()
    assert torch.all(t >= bins[:, :1]) and torch.all(t <= bins[:, -1:])
    assert torch.all(t[:, 1:] >= t[:, :-1])


@pytest.mark.parametrize("hot", [0, 4, 9])
def test_one_hot_weights_at_either_end_put_every_sample_in_that_bin(hot: int) -> None:
    bins = torch.linspace(0.0, 10.0, 11, dtype=torch.float64)[None]
    w = torch.zeros(1, 10, dtype=torch.float64)
    w[0, hot] = 1.0
    t = sample_pdf(bins, w, 32, deterministic=True)
    # the 1e-5 floor leaves 9e-5 of the mass elsewhere: at most one quantile of 32 can fall outside
    inside = ((t >= hot) & (t <= hot + 1)).sum().item()
    assert inside >= 31


def test_stratified_with_near_zero_and_far_beyond_the_scene() -> None:
    near, far = torch.tensor([0.0, 1e-9, 1e-9]), torch.tensor([1e-9, 1e6, 1e-9])
    t = stratified(near, far, 64, jitter=True, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(t).all() and torch.all(t >= near[:, None]) and torch.all(t <= far[:, None])
    assert torch.all(t[:, 1:] >= t[:, :-1])


# ----------------------------------------------------------------------------------------- rendering
@pytest.mark.parametrize("dtype", DTYPES)
def test_near_zero_far_beyond_scene_with_a_surface_renders_it(dtype: torch.dtype) -> None:
    t = stratified(torch.tensor([1e-9], dtype=dtype), torch.tensor([1e6], dtype=dtype), 64, False)
    sigma = torch.full_like(t, 1e-12)
    sigma[0, 10] = 1e12  # an opaque surface in the middle of a 1e6-long ray
    rgb = torch.rand(1, 64, 3, dtype=dtype)
    out = render_dense(sigma, rgb, t, torch.tensor([1e6], dtype=dtype), torch.ones(3, dtype=dtype))
    assert all(torch.isfinite(v).all() for v in out.values())
    torch.testing.assert_close(out["rgb"][0], rgb[0, 10], atol=1e-5, rtol=0)
    assert out["depth"].item() == pytest.approx(t[0, 10].item(), rel=1e-5)


def test_rays_that_miss_the_box_show_the_background_in_both_layouts() -> None:
    # a miss: near == far, so every interval has zero length (dense) or the ray has no samples (packed)
    t = torch.full((2, 8), 3.0)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.8, 0.7]])
    out = render_dense(torch.full((2, 8), 1e12), torch.rand(2, 8, 3), t, torch.full((2,), 3.0), bg)
    torch.testing.assert_close(out["rgb"], bg)
    assert torch.all(out["opacity"] == 0) and torch.all(out["depth"] == 3.0)
    packed = render_packed(torch.zeros(0), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long), 2, bg)
    torch.testing.assert_close(packed["rgb"], bg)
    assert torch.all(packed["depth"] == 0) and torch.all(packed["opacity"] == 0)


@pytest.mark.parametrize("regime", ["faint", "opaque", "tiny_spacing", "huge_spacing"])
def test_gradcheck_dense_at_the_extremes(regime: str) -> None:
    # float64 finite differences agree with autograd where the function is smooth (tau below TAU_MAX, and
    # sigma > eps so the step does not cross the clamp at 0)
    g = torch.Generator().manual_seed(4)
    sig_scale, spacing = {"faint": (1e-3, 1.0), "opaque": (8.0, 1.0), "tiny_spacing": (1e6, 1e-6), "huge_spacing": (1e-3, 1e3)}[regime]
    sigma = ((torch.rand(2, 4, generator=g, dtype=torch.float64) + 0.5) * sig_scale).requires_grad_()
    rgb = torch.rand(2, 4, 3, generator=g, dtype=torch.float64).requires_grad_()
    # t on the scale of the spacing so a finite-difference step of 1e-6 * spacing is resolvable in float64
    t = (spacing * (1.0 + torch.cumsum(torch.rand(2, 4, generator=g, dtype=torch.float64) + 0.5, -1))).requires_grad_()
    far = t.detach()[:, -1] + spacing

    def f(sigma, rgb, t):
        out = render_dense(sigma, rgb, t, far, torch.full((3,), 0.5, dtype=torch.float64))
        return out["rgb"], out["depth"], out["opacity"]

    assert torch.autograd.gradcheck(f, (sigma, rgb, t), eps=1e-6 * min(spacing, 1.0), atol=1e-5, rtol=1e-3)


# ----------------------------------------------------------------------------------------- mixed precision
def test_render_math_is_unchanged_by_bf16_autocast() -> None:
    g = torch.Generator().manual_seed(5)
    sigma = torch.rand(64, 32, generator=g) * 5
    rgb = torch.rand(64, 32, 3, generator=g)
    t = torch.sort(torch.rand(64, 32, generator=g) * 4 + 1, -1).values
    ref = render_dense(sigma, rgb, t, torch.full((64,), 5.5), torch.ones(3))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = render_dense(sigma, rgb, t, torch.full((64,), 5.5), torch.ones(3))
    for k in ref:
        assert mixed[k].dtype == torch.float32, k
        torch.testing.assert_close(mixed[k], ref[k], rtol=0, atol=0, msg=k)


def _rays(n: int = 64) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(6)
    o = torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, -3.0, 0.0])
    d = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, 0.0]) + 0.2 * torch.randn(n, 3, generator=g), dim=-1)
    return o, d, torch.full((n,), 1.5), torch.full((n,), 4.5)


@pytest.mark.parametrize("make", [
    lambda: ClassicModel(torch.tensor([[-1.0] * 3, [1.0] * 3]), n_coarse=16, n_fine=16, pos_freqs=6, dir_freqs=2, depth=3, width=64, skip=0),
    lambda: FastModel(FastConfig(aabb=((-1.0,) * 3, (1.0,) * 3), density_res=32, feature_res=32, occupancy_res=16, init_alpha=0.2)),
], ids=["classic", "fast"])
def test_models_under_bf16_autocast_composite_in_float32(make) -> None:
    torch.manual_seed(0)
    model = make().eval()
    o, d, near, far = _rays()
    with torch.no_grad():
        ref = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
    for k in ("rgb", "depth", "opacity"):
        assert mixed[k].dtype == torch.float32, k
        assert torch.isfinite(mixed[k]).all(), k
    assert (mixed["opacity"] <= 1 + 1e-6).all()
    # bf16 networks (8-bit mantissa) move colors by ~1e-2 at most; compositing itself adds nothing
    torch.testing.assert_close(mixed["rgb"], ref["rgb"], atol=3e-2, rtol=0)
