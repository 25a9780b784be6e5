"""Steps of constant length in contracted space (recon.nerf.contraction.contracted_intervals) for unbounded scenes."""
from __future__ import annotations

import math

import pytest
import torch

from recon.nerf.contraction import contract, contracted_intervals
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
