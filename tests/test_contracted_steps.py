"""Steps of constant length in contracted space (recon.nerf.contraction.contracted_intervals) for unbounded scenes."""
from __future__ import annotations

import math

import pytest
import torch

from recon.nerf.contraction import contract, contracted_distance, contracted_intervals
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.occupancy import march


def _rays() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    o = torch.tensor([[0.0, 0.0, 3.0], [0.2, 0.1, 2.5], [0.3, -0.2, 0.1], [-4.0, 2.0, 6.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.1, 0.05, -1.0], [1.0, 0.3, 0.2], [0.6, -0.3, -1.0]])
    d = d / d.norm(dim=-1, keepdim=True)
    return o, d, torch.tensor([0.5, 0.3, 0.0, 1.0]), torch.tensor([20.0, 10.0, 50.0, 40.0])


def test_radial_ray_takes_equal_steps_in_contracted_space():
    # the ray down the z axis from (0, 0, 3): ||x||_inf = |3 - t|, so its contracted image is a straight segment
    # and each interval must span exactly `step` of it (world steps of step * r^2 outside the unit box)
    o, d = torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    step = 0.02
    ts, te, ri = contracted_intervals(o, d, torch.tensor([0.5]), torch.tensor([20.0]), step, 4096, jitter=False)
    z0, z1 = contract(o + d * ts[:, None].double().float())[:, 2], contract(o + d * te[:, None])[:, 2]
    lengths = (z0 - z1).abs()[:-1]  # the last interval is cut at far
    assert torch.allclose(lengths, torch.full_like(lengths, step), atol=2e-5)
    # count: contracted depth 2 - 1/2.5 (t = 0.5 -> 1) + 2 (unit box) + 1 - 1/17 (t = 4 -> 20), in steps
    expected = ((2 - 1 / 2.5 - 1) + 2 + (1 - 1 / 17)) / step
    assert len(ts) == math.ceil(expected - 1e-6)
    assert ts[0] == pytest.approx(0.5) and te[-1] == pytest.approx(20.0)
    assert torch.equal(ri, torch.zeros_like(ri))


def test_intervals_tile_each_ray_in_order_and_count_far_fewer_samples_than_world_steps():
    o, d, tn, tf = _rays()
    step = 4.0 / 127 * 0.5  # the fast preset's step: half a voxel of a 128³ grid over the contracted cube
    ts, te, ri = contracted_intervals(o, d, tn, tf, step, 1024, jitter=True)
    assert torch.all(ri[1:] >= ri[:-1])
    for r in range(4):
        a, b = ts[ri == r], te[ri == r]
        assert torch.all(b > a) and torch.allclose(b[:-1], a[1:], atol=1e-4)  # contiguous, ordered
        # jitter leaves a gap of less than one (contracted) step before the first sample; steps vary slowly
        assert tn[r] - 1e-6 <= a[0] < tn[r] + 3 * (b[0] - a[0]) and b[-1] == pytest.approx(float(tf[r]), rel=1e-5)
        mid = o[r] + d[r] * (0.5 * (a + b))[:, None]
        seg = (contract(mid[1:]) - contract(mid[:-1])).norm(dim=-1)
        assert float(seg.max()) < 8 * step  # tangential motion shrinks only by 1/r, so allow a few steps there
    unjittered = contracted_intervals(o, d, tn, tf, step, 1024, jitter=False)
    first = torch.cumsum(torch.bincount(unjittered[2], minlength=4), 0) - torch.bincount(unjittered[2], minlength=4)
    assert torch.allclose(unjittered[0][first], tn)
    world = ((tf - tn) / step).ceil().clamp_max(1024)
    assert len(ts) < 0.4 * float(world.sum())


def test_max_samples_caps_a_ray_and_stretches_its_steps():
    o, d, tn, tf = _rays()
    ts, te, ri = contracted_intervals(o, d, tn, tf, 0.001, 64, jitter=False)
    counts = torch.bincount(ri, minlength=4)
    assert torch.all(counts <= 64) and torch.all(counts >= 63)
    for r in range(4):
        assert te[ri == r][-1] == pytest.approx(float(tf[r]), rel=1e-5)


def test_unbounded_fast_model_marches_contracted_steps_by_default():
    cfg = FastConfig(unbounded=True, density_res=32, feature_res=16, occupancy_res=16)
    assert cfg.unbounded_steps == "contracted"
    model = FastModel(cfg)
    o, d, tn, tf = _rays()
    out = model.render_rays(o, d, tn, tf, training=False)
    old = FastModel(FastConfig(unbounded=True, density_res=32, feature_res=16, occupancy_res=16, unbounded_steps="world"))
    old.load_state_dict(model.state_dict())
    out_old = old.render_rays(o, d, tn, tf, training=False)
    assert out["num_samples"] < 0.5 * out_old["num_samples"]
    # an empty field (initial opacity per step): both see through to nearly the same background
    assert torch.allclose(out["rgb"], out_old["rgb"], atol=0.15)
    ts, te, ri = march(o, d, tn, tf, None, 0.05, 256, contracted=True)
    ts2, te2, ri2 = contracted_intervals(o, d, tn, tf, 0.05, 256, jitter=False)
    assert torch.equal(ri, ri2) and torch.equal(ts, ts2)


def test_contracted_distance_is_the_integral_of_one_over_rho_squared_and_each_contracted_step_spans_one_step():
    torch.manual_seed(0)
    n = 16
    o = torch.randn(n, 3) * 1.5  # some rays start inside the unit box, some outside
    d = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    t_near, t_far = torch.zeros(n), torch.full((n,), 1e4)
    u = torch.linspace(0, 1, 100_001, dtype=torch.float64) ** 4
    for r in range(4):  # against the trapezoid rule on a fine grid of the ray
        t = t_far[r].double() * u
        rho = (o[r].double() + t[:, None] * d[r].double()).abs().amax(-1).clamp_min(1.0)
        integral = torch.cat([torch.zeros(1, dtype=torch.float64),
                              torch.cumsum(0.5 * (rho[1:] ** -2 + rho[:-1] ** -2) * (t[1:] - t[:-1]), 0)])
        s = contracted_distance(o, d, t_near, t_far, t.float(), torch.full_like(t, r, dtype=torch.long))
        assert torch.allclose(s.double(), integral, atol=1e-5)
        assert 0.5 < float(s[-1]) < 4.0  # the far field adds at most a few box widths, however far it runs
    step = 0.01
    ts, te, ri = contracted_intervals(o, d, t_near, t_far, step, 100_000, jitter=False)
    ds = contracted_distance(o, d, t_near, t_far, te, ri) - contracted_distance(o, d, t_near, t_far, ts, ri)
    first = torch.ones_like(ri, dtype=torch.bool)
    first[1:] = ri[1:] != ri[:-1]
    last = torch.ones_like(first)
    last[:-1] = first[1:]
    inner = ~(first | last)  # a ray's last interval is cut at t_far
    assert torch.allclose(ds[inner], torch.full_like(ds[inner], step), rtol=1e-3)


def test_unbounded_distortion_loss_does_not_grow_with_how_far_the_rays_run():
    """Measured in world distance, the loss of a field's weight spread to the far field grows with far; in
    contracted distance it stays the size of an object's."""
    torch.manual_seed(0)
    model = FastModel(FastConfig(unbounded=True, density_res=32, feature_res=16, occupancy_res=16,
                                 unbounded_distortion_weight=1.0))
    o, d, tn, _ = _rays()
    regs = [float(model.render_rays(o, d, tn, torch.full_like(tn, far), training=True)["reg"].detach())
            for far in (1e2, 1e5)]
    assert all(0.0 < r < 2.0 for r in regs) and regs[1] < 1.5 * regs[0]
