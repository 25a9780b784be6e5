"""The Triton kernels (recon.nerf.kernels) against the torch code they replace: forward values and gradients.

Where CUDA is present the kernels run compiled, in this process. Elsewhere, where triton is installed, they run under
Triton's interpreter (numpy on CPU tensors): TRITON_INTERPRET=1 must be set before triton is imported, so
`test_kernels_under_the_interpreter` runs this file again in a subprocess with it set; no other test sees the
variable or an imported triton. Without triton every test here skips. The interpreter is slow (numpy per program),
so the cases are small: a few hundred samples, rays of 0 to 130 samples (across the kernels' 64-sample chunks).
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from recon.nerf import kernels
from recon.nerf.grid import hash_reference, trilinear_levels_torch
from recon.nerf.kernels import (
    accumulate_packed_triton,
    composite_packed_torch,
    composite_packed_triton,
    distortion_packed_triton,
    hash_levels_triton,
    pixel_rays_triton,
    ray_box_triton,
    trilinear_levels_triton,
)
from recon.nerf.rays import ray_aabb_torch
from recon.nerf.render import accumulate_packed, distortion_packed
from tests.odd_rays import BOX, odd_rays, stacked_batcher

REPO = Path(__file__).resolve().parents[1]
HAS_TRITON = importlib.util.find_spec("triton") is not None
INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"
DEVICE = "cpu" if INTERPRETED else "cuda" if torch.cuda.is_available() else None

if not HAS_TRITON:
    pytest.skip("triton is not installed (it comes with the [test] extra on Linux x86_64)", allow_module_level=True)


@pytest.fixture
def device() -> str:
    """Where the kernel cases run: CUDA, compiled; the CPU under the interpreter; else they skip (in one line)."""
    if DEVICE is None:
        pytest.skip("no CUDA: the kernels run under the interpreter (test_kernels_under_the_interpreter)")
    return DEVICE


# ----------------------------------------------------------------------------- cases
def _packed(counts: list[int], seed: int = 0, sigma_scale: float = 20.0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    ri = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    m = ri.shape[0]
    # no density of exactly 0: where every earlier tau of a ray is 0 the reference's float64 running sum minus the
    # ray's start can round below 0, and its clamp then drops that gradient (the kernel's per-ray sum keeps it)
    sigma = torch.rand(m, generator=g) * sigma_scale + 1e-3
    delta = torch.rand(m, generator=g) * 0.1 + 1e-3
    t = torch.cumsum(delta, 0)
    return sigma, delta, t, ri


def _to(device: str, *xs: torch.Tensor, grad: bool = False) -> list[torch.Tensor]:
    return [x.to(device).requires_grad_(grad and x.is_floating_point()) for x in xs]


def _compare_composite(sigma: torch.Tensor, delta: torch.Tensor, t: torch.Tensor, ri: torch.Tensor, n: int,
                       rtol: float = 1e-5, atol: float = 1e-6) -> None:
    """Forward and gradients (to sigma, delta and t, from all four outputs) of the kernel and the reference.

    Gradients within 1e-5 relative, or 1e-6 of the largest: a sample's dL/dtau is its own term minus the later
    samples' sum, which cancel in float32 (the reference's cumulative sum is float64)."""
    s, d, tt = _to(DEVICE, sigma, delta, t, grad=True)
    (r,) = _to(DEVICE, ri)
    fused = composite_packed_triton(s, d, tt, r, n)
    s2, d2, t2 = _to(DEVICE, sigma, delta, t, grad=True)
    reference = composite_packed_torch(s2, d2, t2, r, n)
    for name, a, b in zip(("weights", "transmittance", "opacity", "depth"), fused, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol, msg=lambda m, name=name: f"{name}: {m}")
    g = torch.Generator().manual_seed(1)
    upstream = [torch.randn(x.shape, generator=g).to(DEVICE) for x in reference]
    got = torch.autograd.grad(fused, (s, d, tt), upstream)
    want = torch.autograd.grad(reference, (s2, d2, t2), upstream)
    for name, a, b in zip(("d sigma", "d delta", "d t"), got, want, strict=True):
        scale = float(b.abs().max()) if b.numel() else 1.0
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * max(1.0, scale),
                                   msg=lambda m, name=name: f"{name}: {m}")


def test_composite_matches_render_weights_packed_over_rays_of_varied_length(device: str) -> None:
    counts = [0, 3, 0, 0, 64, 1, 65, 130, 2, 0]  # empty rays first, last and in a row; rays across 64-sample chunks
    for scale in (0.8, 20.0):  # translucent rays (T ~ 0.1 after 130 samples: every chunk counts), then opaque ones
        sigma, delta, t, ri = _packed(counts, sigma_scale=scale)
        _compare_composite(sigma, delta, t, ri, len(counts))


def test_composite_of_opaque_rays_huge_densities_and_zero_intervals(device: str) -> None:
    counts = [5, 70, 4, 6]
    sigma, delta, t, ri = _packed(counts, seed=2)
    sigma[:5] = 1e12  # clamped to SIGMA_MAX: the first sample takes all the weight
    sigma[5:75] = 1e4  # every sample opaque (tau 10..1e3): weights 1, 0, 0, ...
    sigma[76] = float("inf")  # clamped, finite weights
    delta[75:79] = 0.0  # zero intervals: no opacity, no gradient to sigma
    delta[80] = -0.5  # a negative interval counts as zero
    _compare_composite(sigma, delta, t, ri, len(counts))
    w, _, opacity, _ = composite_packed_triton(*_to(DEVICE, sigma, delta, t, ri), len(counts))
    assert torch.isfinite(w).all() and opacity[:2].tolist() == pytest.approx([1.0, 1.0])
    assert float(w[0]) == pytest.approx(1.0) and float(w[1:5].abs().max()) == 0.0


def test_composite_of_thin_media_keeps_expm1_accuracy(device: str) -> None:
    """tau down to 1e-9: alpha = -expm1(-tau) ~ tau, where 1 - exp(-tau) rounds to 0 or to one ulp of 1."""
    counts = [40, 40]
    sigma, delta, t, ri = _packed(counts, seed=3)
    sigma = torch.logspace(-8, 0.5, 80) / delta  # tau from 1e-8 to ~3, across the series' switch at 0.5
    _compare_composite(sigma, delta, t, ri, len(counts), rtol=2e-6, atol=1e-12)


def test_composite_without_samples_and_without_rays(device: str) -> None:
    empty = torch.zeros(0)
    w, tr, opacity, depth = composite_packed_triton(*_to(DEVICE, empty, empty, empty, empty.long()), 3)
    assert w.shape == tr.shape == (0,) and opacity.tolist() == depth.tolist() == [0.0, 0.0, 0.0]
    assert composite_packed_triton(*_to(DEVICE, empty, empty, empty, empty.long()), 0)[2].shape == (0,)


def test_a_nan_density_reaches_the_weights(device: str) -> None:
    """A diverged network's NaN must show (the trainer's guard names it), not be clamped away."""
    sigma, delta, t, ri = _packed([4, 4])
    sigma[1] = float("nan")
    w, _, opacity, _ = composite_packed_triton(*_to(DEVICE, sigma, delta, t, ri), 2)
    assert torch.isnan(w[1:4]).all() and torch.isnan(opacity[0]) and torch.isfinite(w[4:]).all()


def _compare_distortion(w: torch.Tensor, mid: torch.Tensor, delta: torch.Tensor, ri: torch.Tensor, n: int) -> None:
    """Each ray's loss and its gradients to the weights, midpoints and intervals: the float32 kernel against the
    reference run in float64 (the truth the float32 reference is also held to: both cancel in m W_<i - (wm)_<i)."""
    mine = _to(DEVICE, w, mid, delta, grad=True)
    ref = _to(DEVICE, w.double(), mid.double(), delta.double(), grad=True)
    (r,) = _to(DEVICE, ri)
    got, want = distortion_packed_triton(*mine, r, n), distortion_packed(*ref, r, n)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), want, rtol=1e-6, atol=1e-6)
    up = torch.randn(n, generator=torch.Generator().manual_seed(5), dtype=torch.float64).to(DEVICE)
    for name, a, b in zip(("d weights", "d midpoints", "d intervals"), torch.autograd.grad(got, mine, up.float()),
                          torch.autograd.grad(want, ref, up), strict=True):
        torch.testing.assert_close(a.double(), b, rtol=1e-6, atol=1e-6 * max(1.0, float(b.abs().max())),
                                   msg=lambda m, name=name: f"{name}: {m}")


def test_distortion_matches_the_reference_over_rays_of_varied_length(device: str) -> None:
    counts = [0, 3, 0, 0, 64, 1, 65, 130, 2, 0]
    sigma, delta, t, ri = _packed(counts, sigma_scale=5.0)
    w, _ = composite_packed_torch(sigma, delta, t, ri, len(counts))[:2]
    _compare_distortion(w, t - 0.5 * delta, delta, ri, len(counts))
    # far from the origin (an unbounded capture's contracted distances near 2), weights not from compositing
    g = torch.Generator().manual_seed(4)
    _compare_distortion(torch.rand(ri.shape[0], generator=g), 1.5 + 0.2 * t / t.max(), delta, ri, len(counts))


def test_distortion_without_samples_without_rays_and_of_one_sample(device: str) -> None:
    empty = torch.zeros(0)
    assert distortion_packed_triton(*_to(DEVICE, empty, empty, empty, empty.long()), 3).tolist() == [0.0] * 3
    assert distortion_packed_triton(*_to(DEVICE, empty, empty, empty, empty.long()), 0).shape == (0,)
    one = torch.tensor([0.5]), torch.tensor([1.0]), torch.tensor([0.3]), torch.tensor([1])
    got = distortion_packed_triton(*_to(DEVICE, *one), 2)  # a lone sample: only its own interval's term
    assert got.tolist() == pytest.approx([0.0, 0.25 * 0.3 / 3])


@pytest.mark.parametrize("channels", [3, 1, 0])
def test_accumulate_matches_index_add(device: str, channels: int) -> None:
    counts = [0, 2, 65, 0, 7, 0]
    _, _, _, ri = _packed(counts)
    g = torch.Generator().manual_seed(4)
    w = torch.rand(ri.shape[0], generator=g)
    v = torch.rand(ri.shape[0], channels, generator=g) if channels else torch.rand(ri.shape[0], generator=g)
    w1, v1, w2, v2 = _to(DEVICE, w, v, w, v, grad=True)
    (r,) = _to(DEVICE, ri)
    got, want = accumulate_packed_triton(w1, v1, r, len(counts)), accumulate_packed(w2, v2, r, len(counts))
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    up = torch.randn(want.shape, generator=g).to(DEVICE)
    for a, b in zip(torch.autograd.grad(got, (w1, v1), up), torch.autograd.grad(want, (w2, v2), up), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def _points(m: int, seed: int = 5) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(m, 3, generator=g)
    x[:8] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 1], [0, 1, 0.5], [0.5, 1, 0], [-0.2, 0.3, 1.4],
                          [1e-7, 1 - 1e-7, 0.5], [0.25, 0.5, 0.75]])  # corners, faces, outside (clamped), a vertex
    return x


@pytest.mark.parametrize("channels, resolutions", [(1, [5, 9, 17]), (12, [7]), (2, [3, 4, 5, 6, 7])],
                         ids=["density-levels", "feature-grid", "five-levels"])
def test_trilinear_levels_match_the_grids_torch_reads(device: str, channels: int, resolutions: list[int]) -> None:
    g = torch.Generator().manual_seed(6)
    tables = [torch.randn(r**3, channels, generator=g) for r in resolutions]
    x = _points(200).to(DEVICE)
    mine = [t.to(DEVICE).requires_grad_() for t in tables]
    ref = [t.to(DEVICE).requires_grad_() for t in tables]
    got, want = trilinear_levels_triton(x, mine, resolutions), trilinear_levels_torch(x, ref, resolutions)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    up = torch.randn(want.shape, generator=g).to(DEVICE)
    for a, b in zip(torch.autograd.grad(got, mine, up), torch.autograd.grad(want, ref, up), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("max_res, log2_table", [(24, 10), (64, 12)], ids=["some-levels-hashed", "most-hashed"])
def test_hash_levels_match_the_hash_grids_torch_read(device: str, max_res: int, log2_table: int) -> None:
    """Dense levels and hashed ones (tables small enough that vertices collide), points on the box's faces and
    corners and outside it among them: the same features and the same table gradient (collisions sum, as the torch
    gather's do)."""
    from recon.nerf.grid import HashGrid

    torch.manual_seed(2)
    grid = HashGrid(levels=6, features=2, log2_table=log2_table, base_res=4, max_res=max_res, init_scale=1.0)
    assert any(grid.hashed) and not all(grid.hashed)
    grid = grid.to(DEVICE)
    x = _points(200).to(DEVICE)
    got = hash_levels_triton(x, grid.table, grid.verts_t, grid.offsets, grid.hashed_t, grid.log2_table)
    want = grid.read_torch(x)  # the reference
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    up = torch.randn(want.shape, generator=torch.Generator().manual_seed(3)).to(DEVICE)
    (a,) = torch.autograd.grad(got, grid.table, up)
    (b,) = torch.autograd.grad(want, grid.table, up)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_the_hash_kernels_probe_agrees_where_it_runs(device: str) -> None:
    from recon.nerf.grid import hash_kernel_check

    hash_kernel_check.cache_clear()
    ok, why = hash_kernel_check(DEVICE)
    assert ok and "one Triton kernel" in why, why


def test_a_hash_kernel_that_fails_leaves_hash_grids_to_the_torch_read(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the kernel cannot be built (or disagrees), the probe says so once and the grid reads in torch."""
    import recon.nerf.grid as grid_module
    from recon.nerf.grid import HashGrid, hash_kernel_check

    def broken(*args: Any) -> torch.Tensor:
        raise RuntimeError("PTX assembly aborted\nmore lines")

    monkeypatch.setattr(kernels, "KERNEL_DEVICES", ("cuda", "cpu"))
    monkeypatch.setattr(grid_module, "hash_levels_triton", broken)
    hash_kernel_check.cache_clear()
    try:
        ok, why = hash_kernel_check("cpu")
        assert not ok and "failed" in why and "PTX assembly aborted" in why and "more lines" not in why
        grid = HashGrid(levels=3, features=2, log2_table=8, base_res=4, max_res=20, init_scale=1.0)
        grid.kernels = "triton"
        x = _points(50)
        torch.testing.assert_close(grid(x), hash_reference(grid, x), rtol=1e-5, atol=1e-5)
    finally:
        hash_kernel_check.cache_clear()


@pytest.mark.parametrize("features", ["dense", "hash"])
def test_fast_model_renders_and_trains_the_same_through_the_kernels(device: str, monkeypatch: pytest.MonkeyPatch,
                                                                    features: str) -> None:
    """One training render of a small fast model, train.fast.kernels=triton against torch from the same weights:
    the same colours, depths, opacities and grid gradients (on a CPU: under the interpreter, the C marcher's
    samples for both). Colour features in a dense grid of two levels or in a hash grid."""
    from recon.nerf.fast import FastConfig, FastModel

    monkeypatch.setattr(kernels, "KERNEL_DEVICES", ("cuda", "cpu") if INTERPRETED else ("cuda",))
    # two levels of 17³ and 33³ each (none under MultiDenseGrid's 16³): the levels read in one pass
    cfg = dict(density_res=33, feature_res=33, feature_dim=4, density_levels=2, feature_levels=2, mlp_width=8,
               occupancy_res=8, occupancy_warmup=0, early_stop_transmittance=0.0, init_alpha=0.3,
               color_min_weight=0.0,  # every sample coloured: a weight at the threshold can't pick different samples
               distortion_weight=0.05, grid=features, hash_table_log2=10)
    torch.manual_seed(0)
    reference = FastModel(FastConfig(**cfg, kernels="torch")).to(DEVICE)
    with torch.no_grad():
        for p in reference.parameters():
            p.add_(0.5 * torch.randn_like(p))
    fused = FastModel(FastConfig(**cfg, kernels="triton")).to(DEVICE)
    fused.load_state_dict(reference.state_dict())
    assert len(fused.density_grid.grids) == 2
    assert len(fused.color_grid.grids) == 2 if features == "dense" else any(fused.color_grid.hashed)
    g = torch.Generator().manual_seed(7)
    toward = torch.randn(6, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -1.0])
    rays_d = torch.nn.functional.normalize(toward, dim=-1)
    rays_o = torch.tensor([0.0, 0.0, 2.5]) + 0.3 * torch.randn(6, 3, generator=g)
    rays = [x.to(DEVICE) for x in (rays_o, rays_d, torch.full((6,), 0.5), torch.full((6,), 4.5))]
    outs = []
    for model in (reference, fused):
        torch.manual_seed(3)  # the same jitter
        out = model.render_rays(*rays, training=True, background=torch.ones(3, device=DEVICE))
        (out["rgb"].square().sum() + out["depth"].sum() + out["opacity"].sum() + out["reg"]).backward()
        outs.append(out)
    assert outs[0]["num_samples"] == outs[1]["num_samples"] > 0
    for key in ("rgb", "depth", "opacity", "reg"):
        torch.testing.assert_close(outs[1][key], outs[0][key], rtol=1e-5, atol=1e-5)
    for (name, a), b in zip(fused.named_parameters(), reference.parameters(), strict=True):
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-5, msg=lambda m, name=name: f"{name}: {m}")


def _ball_field(levels: int, activation: str) -> tuple[Any, tuple[torch.Tensor, ...]]:
    """A small fast model holding a noisy opaque ball on ``levels`` dense density grids, its occupancy refreshed
    (some cells empty), on DEVICE; and rays from a camera looking at it, every 17th with an empty segment."""
    from recon.nerf.fast import FastConfig, FastModel
    from recon.nerf.rays import camera_rays, ray_aabb

    torch.manual_seed(0)
    cfg = FastConfig(aabb=((-1.0, -1.2, -0.8), (1.1, 1.0, 1.0)), density_res=20, feature_res=8, feature_dim=4,
                     density_levels=levels, occupancy_res=12, density_activation=activation, kernels="triton")
    model = FastModel(cfg)
    with torch.no_grad():
        grids = model.density_grid.grids if levels > 1 else [model.density_grid]
        for i, grid in enumerate(grids):
            lin = torch.linspace(-1.0, 1.0, grid.res)
            x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
            raw = (40.0 if i == 0 else 4.0) * (0.6 - (x**2 + y**2 + z**2).sqrt()) + 0.5 * torch.randn_like(x)
            grid.table.copy_(raw.reshape(-1, 1) / len(grids))
    model.occupancy.warmup_steps = 0
    model.occupancy.update(model.density, 100)
    model = model.to(DEVICE).eval()
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 3.0])
    o, d = camera_rays(c2w, 110.0, 110.0, 6.0, 6.0, 12, 12)
    o, d = o.reshape(-1, 3).to(DEVICE), d.reshape(-1, 3).to(DEVICE)
    tn, tf, hit = ray_aabb(o, d, model.aabb)
    tn = tn.clamp_min(0.5)
    tf = torch.where(hit, tf, tn)
    tf[::17] = tn[::17]  # empty segments among the rays
    return model, (o, d, tn, tf)


@pytest.mark.parametrize("levels, activation, jitter, max_samples",
                         [(3, "softplus", True, 1024), (1, "trunc_exp", False, 1024), (2, "softplus", True, 9)],
                         ids=["three-levels-jittered", "one-level-exp", "capped-at-9-steps"])
def test_march_matches_the_torch_front_to_back_march(device: str, monkeypatch: pytest.MonkeyPatch, levels: int,
                                                     activation: str, jitter: bool, max_samples: int) -> None:
    """The Triton marcher keeps the samples march_front_to_back keeps: the same rays, intervals and densities, in the
    same order (under the interpreter exactly; compiled, a multiply-add may move a midpoint across a cell's face by
    a rounding, so 1 ray in 100 may differ)."""
    from recon.nerf.kernels import march_dense_triton
    from recon.nerf.occupancy import march_front_to_back

    monkeypatch.setattr(kernels, "KERNEL_DEVICES", ("cuda", "cpu") if INTERPRETED else ("cuda",))
    model, (o, d, tn, tf) = _ball_field(levels, activation)
    occupied = model.occupancy.occupied
    assert 0 < int(occupied.sum()) < occupied.numel()  # empty cells to skip

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model._sigma_unit(model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0))

    torch.manual_seed(3)
    ref = march_front_to_back(o, d, tn, tf, model.occupancy, model.step_size, max_samples, sigma_fn, jitter=jitter,
                              min_transmittance=1e-3)
    torch.manual_seed(3)
    with torch.no_grad():
        got = march_dense_triton(o, d, tn, tf, jitter, model._dense_density(), model.step_size, max_samples, 1e-3)
    assert got is not None
    n = o.shape[0]
    counts = [torch.bincount(x[2], minlength=n) for x in (got, ref)]
    assert int(counts[1].sum()) > 2 * n and int((counts[1] == 0).sum()) > 0  # rays through the ball, rays that miss
    same = counts[0] == counts[1]
    assert float(same.float().mean()) >= (1.0 if INTERPRETED else 0.99), f"{int((~same).sum())} of {n} rays differ"
    keep = [same[x[2]] for x in (got, ref)]
    assert torch.equal(got[2][keep[0]], ref[2][keep[1]])
    for a, b in zip(got[:2], ref[:2]):
        torch.testing.assert_close(a[keep[0]], b[keep[1]], atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(got[3][keep[0]], ref[3][keep[1]], atol=1e-3, rtol=1e-4)


def test_march_of_no_rays_and_of_rays_that_miss(device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from recon.nerf.kernels import march_dense_triton

    monkeypatch.setattr(kernels, "KERNEL_DEVICES", ("cuda", "cpu") if INTERPRETED else ("cuda",))
    model, (o, d, tn, tf) = _ball_field(2, "softplus")
    field = model._dense_density()
    for rays in ((o[:0], d[:0], tn[:0], tf[:0]), (o[:5], d[:5], tn[:5], tn[:5] - 1.0)):
        ts, te, ri, sigma = march_dense_triton(*rays, True, field, model.step_size, 1024, 1e-3)
        assert ts.shape == te.shape == ri.shape == sigma.shape == (0,)


# ----------------------------------------------------------------------------- rays
def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal values, NaN where NaN (torch.equal counts NaN unequal)."""
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0))


def test_ray_box_kernel_is_the_torch_ray_box(device: str) -> None:
    """Bit for bit: the kernel divides rounded to nearest, as torch does."""
    o, d, near, far = (x.to(device) for x in odd_rays())
    box = BOX.to(device)
    fused = ray_box_triton(o, d, box)
    reference = ray_aabb_torch(o, d, box)
    assert int(reference[2].sum()) > 300
    for a, b in zip(fused, reference, strict=True):
        assert a.dtype == b.dtype and _same(a, b)
    t_near, t_far, _ = ray_box_triton(o, d, box, near, far)
    tn, tf, hit = reference
    clipped_near = torch.maximum(near, tn)
    assert _same(t_near, clipped_near)
    assert _same(t_far, torch.where(hit, torch.minimum(far, tf), clipped_near))
    assert all(x.shape == (0,) for x in ray_box_triton(o[:0], d[:0], box))


@pytest.mark.parametrize("box", [True, False])
def test_pixel_rays_kernel_makes_the_torch_batch(device: str, box: bool) -> None:
    batcher = stacked_batcher(box)
    flat = torch.arange(batcher.n_rays).flip(0)
    args = [None if t is None else t.to(device) for t in (flat, batcher.offsets, batcher._widths, batcher.c2w,
                                                          batcher.intrinsics, batcher.aabb, batcher.near_far)]
    o, d, near, far, hit, img = (x.cpu() for x in pixel_rays_triton(*args))
    o_t, d_t, near_t, far_t, hit_t, img_t = batcher._rays_torch(flat)
    assert torch.equal(img, img_t) and torch.equal(o, o_t) and img.unique().numel() == 5
    # fused multiply-adds in the kernel's rotation: the directions to a rounding
    torch.testing.assert_close(d, d_t, rtol=0, atol=3e-7)
    assert torch.equal(hit, hit_t)
    torch.testing.assert_close(near, near_t, rtol=2e-6, atol=2e-6)
    torch.testing.assert_close(far, far_t, rtol=2e-6, atol=2e-6)


# ----------------------------------------------------------------------------- the interpreter run
@pytest.mark.skipif(INTERPRETED, reason="this is the interpreter run")
@pytest.mark.skipif(DEVICE == "cuda", reason="CUDA is here: the kernel cases ran compiled, the code the train stage runs")
def test_kernels_under_the_interpreter() -> None:
    """This file again with TRITON_INTERPRET=1 in a fresh process: every kernel case on CPU tensors, where no GPU
    compiles them (on an H100 machine, triton 3.6's interpreter failed on numpy 2.5, while the compiled cases passed)."""
    env = {**os.environ, "TRITON_INTERPRET": "1"}
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                          str(Path(__file__).relative_to(REPO))], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=600)
    shown = run.stdout[-6000:] + run.stderr[-3000:]
    assert run.returncode == 0, shown
    last = run.stdout.strip().splitlines()[-1]
    assert " passed" in last and "failed" not in last and "error" not in last, shown
