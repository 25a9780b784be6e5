"""Occupancy grid and packed marching: never culls occupied space; packed layout; early termination."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from recon.nerf.grid import trilinear_reference
from recon.nerf.occupancy import OccupancyGrid, cells_with_a_vertex, density_threshold, march

AABB = torch.tensor([[-1.0, -0.5, -1.5], [1.0, 1.5, 0.5]])


def test_density_threshold_closed_form() -> None:
    sigma = density_threshold(0.01, 0.02)
    assert math.isclose(1.0 - math.exp(-sigma * 0.02), 0.01, rel_tol=1e-12)


def _vertex_field(values: torch.Tensor, aabb: torch.Tensor):
    """Density trilinear between the occupancy grid's vertices: values (R+1, R+1, R+1)."""

    def fn(x: torch.Tensor) -> torch.Tensor:
        u = ((x - aabb[0]) / (aabb[1] - aabb[0])).clamp(0, 1)
        return trilinear_reference(values[..., None], u)[:, 0]

    return fn


@settings(max_examples=30, deadline=None)
@given(
    res=st.integers(min_value=2, max_value=6),
    seed=st.integers(min_value=0, max_value=2**31 - 1),
    sparsity=st.floats(min_value=0.5, max_value=0.98),
)
def test_grid_never_culls_where_the_field_is_above_threshold(res: int, seed: int, sparsity: float) -> None:
    g = torch.Generator().manual_seed(seed)
    values = torch.rand((res + 1,) * 3, generator=g, dtype=torch.float64)
    values = torch.where(values > sparsity, values * 50, values * 0.01)  # a few dense vertices
    field = _vertex_field(values, AABB.double())
    thr = 1.0
    occ = OccupancyGrid(AABB, resolution=res, sigma_threshold=thr, warmup_steps=0).double()
    occ.update(field, step=0)
    # any point: density above the threshold => its cell is occupied
    x = AABB[0] + torch.rand(4000, 3, generator=g, dtype=torch.float64) * (AABB[1] - AABB[0])
    dense = field(x) > thr
    assert bool(occ.query(x)[dense].all())
    # and the marcher keeps every sample whose midpoint is above the threshold
    o = AABB[0] - 0.3 + torch.rand(64, 3, generator=g, dtype=torch.float64) * (AABB[1] - AABB[0] + 0.6)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    t_near, t_far = torch.zeros(64, dtype=torch.float64), torch.full((64,), 4.0, dtype=torch.float64)
    _, _, ri_all = march(o, d, t_near, t_far, None, 0.05, 1000)
    ts_all, te_all, _ = march(o, d, t_near, t_far, None, 0.05, 1000)
    mid_all = 0.5 * (ts_all + te_all)
    inside = ((o[ri_all] + d[ri_all] * mid_all[:, None] - AABB[0]) >= 0).all(-1) & (
        (o[ri_all] + d[ri_all] * mid_all[:, None] - AABB[1]) <= 0
    ).all(-1)
    need = inside & (field(o[ri_all] + d[ri_all] * mid_all[:, None]) > thr)
    ts, te, ri = march(o, d, t_near, t_far, occ, 0.05, 1000)
    kept = set(zip(ri.tolist(), [round(v, 9) for v in ts.tolist()]))
    needed = set(zip(ri_all[need].tolist(), [round(v, 9) for v in ts_all[need].tolist()]))
    assert needed <= kept


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**31 - 1), st.floats(0.0, 1.0))
def test_a_cell_is_occupied_when_any_of_its_corners_is_above(nx: int, ny: int, nz: int, seed: int, share: float) -> None:
    """The separable OR against a max-pool of 2, stride 1 (the plain definition) on any grid shape, and one vertex
    set occupies exactly the cells around it."""
    above = torch.rand(nx + 1, ny + 1, nz + 1, generator=torch.Generator().manual_seed(seed)) < share
    pooled = torch.nn.functional.max_pool3d(above.float()[None, None], kernel_size=2, stride=1)[0, 0] > 0
    assert torch.equal(cells_with_a_vertex(above), pooled)
    one = torch.zeros(5, 5, 5, dtype=torch.bool)
    one[2, 0, 4] = True
    cells = cells_with_a_vertex(one)
    assert cells.shape == (4, 4, 4) and set(map(tuple, cells.nonzero().tolist())) == {
        (i, 0, 3) for i in (1, 2)}


def test_ema_keeps_the_max_of_decayed_history_and_warmup_counts_all() -> None:
    occ = OccupancyGrid(AABB, resolution=4, sigma_threshold=0.5, decay=0.5, warmup_steps=10)
    occ.update(lambda x: torch.full((x.shape[0],), 4.0), step=0)
    assert bool(occ.occupied.all())
    occ.update(lambda x: torch.zeros(x.shape[0]), step=1)
    torch.testing.assert_close(occ.ema, torch.full_like(occ.ema, 2.0))
    occ.update(lambda x: torch.zeros(x.shape[0]), step=20)  # ema 1.0 > 0.5 still occupied
    assert bool(occ.occupied.all())
    corner = lambda x: torch.where((x <= AABB[0] + 1e-6).all(dim=-1), 4.0, 0.0)  # noqa: E731 (the object)
    for step in range(21, 23):
        occ.update(corner, step=step)  # 0.5, 0.25 elsewhere: below -> empty
    assert int(occ.occupied.sum()) == 1 and bool(occ.occupied[0, 0, 0])
    assert bool(occ.warm)


def test_threshold_ramps_from_start_to_final_after_warmup() -> None:
    """A density between the start and the final threshold stays occupied early in the ramp and is culled once
    the ramp has reached it: a young object keeps its samples while its density rises."""
    occ = OccupancyGrid(AABB, resolution=4, sigma_threshold=5.0, warmup_steps=10, start_threshold=1.0, ramp_steps=100)
    assert [occ.threshold_at(s) for s in (0, 10, 60, 110, 500)] == [1.0, 1.0, 3.0, 5.0, 5.0]
    occ.decay = 0.0  # the EMA is the last density: each update's threshold alone decides

    def field(x: torch.Tensor) -> torch.Tensor:  # 2.0 everywhere but a dense corner vertex (the object)
        return torch.where((x <= AABB[0] + 1e-6).all(dim=-1), 10.0, 2.0)

    occ.update(field, step=20)  # threshold 1.8
    assert bool(occ.occupied.all())
    occ.update(field, step=40)  # threshold 2.6
    assert int(occ.occupied.sum()) == 1 and bool(occ.occupied[0, 0, 0]) and not occ.faint
    plain = OccupancyGrid(AABB, resolution=4, sigma_threshold=5.0, warmup_steps=10)
    assert plain.threshold_at(11) == 5.0


def test_a_refresh_that_would_cull_everything_leaves_the_grid_open() -> None:
    """A young field below the threshold everywhere keeps every cell it had (all of them after the warm-up) and
    says so (``faint``); once part of it passes the threshold, the threshold alone decides again."""
    occ = OccupancyGrid(AABB, resolution=20, sigma_threshold=5.0, warmup_steps=0)
    occ.decay = 0.0
    centre = AABB.mean(dim=0)

    def bump(peak: float):  # densest at the box centre, fading outwards
        return lambda x: peak * torch.exp(-((x - centre) ** 2).sum(-1) / 0.5)

    occ.update(bump(1.0), step=0)  # below 5 everywhere
    assert occ.faint and bool(occ.occupied.all()) and not bool(occ.warm)
    occ.update(bump(100.0), step=1)  # the field has grown: above 5 near the centre only
    assert not occ.faint and bool(occ.warm) and bool(occ.occupied[10, 10, 10]) and not bool(occ.occupied[0, 0, 0])
    before = occ.occupied.clone()
    occ.update(lambda x: torch.zeros(x.shape[0]), step=2)  # nothing above: the grid stays as it was
    assert occ.faint and torch.equal(occ.occupied, before)


def test_update_share_covers_every_vertex() -> None:
    occ = OccupancyGrid(AABB, resolution=5, warmup_steps=0)
    seen = torch.zeros(6**3, dtype=torch.long)

    def fn(x: torch.Tensor) -> torch.Tensor:
        u = (x - AABB[0]) / (AABB[1] - AABB[0]) * 5
        ijk = u.round().long()
        seen.index_add_(0, (ijk[:, 0] * 6 + ijk[:, 1]) * 6 + ijk[:, 2], torch.ones(x.shape[0], dtype=torch.long))
        return torch.zeros(x.shape[0])

    for step in range(4):
        occ.update(fn, step, share=4)
    assert bool((seen == 1).all())


def test_occupied_aabb_and_outside_points() -> None:
    occ = OccupancyGrid(AABB, resolution=4, sigma_threshold=1.0, warmup_steps=0)
    occ.occupied.fill_(False)
    assert occ.occupied_aabb() is None and occ.occupied_fraction() == 0.0
    occ.occupied[1, 2, 3] = True
    box = occ.occupied_aabb()
    size = (AABB[1] - AABB[0]) / 4
    torch.testing.assert_close(box, torch.stack([AABB[0] + size * torch.tensor([1, 2, 3]), AABB[0] + size * torch.tensor([2, 3, 4])]))
    assert not bool(occ.query(torch.tensor([[5.0, 0.0, 0.0]]))[0])


def test_march_uniform_packed_layout() -> None:
    o = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    t_near = torch.tensor([0.5, 1.0, 2.0])
    t_far = torch.tensor([1.0, 1.0, 2.35])  # second ray empty
    ts, te, ri = march(o, d, t_near, t_far, None, 0.1, 100)
    assert ri.tolist() == [0] * 5 + [2] * 4
    torch.testing.assert_close(ts[:5], torch.tensor([0.5, 0.6, 0.7, 0.8, 0.9]))
    torch.testing.assert_close(te[-1], torch.tensor(2.35))  # last interval clipped to t_far
    torch.testing.assert_close(ts[1:5], te[:4])  # contiguous


def test_march_respects_max_samples_and_jitter_stays_inside() -> None:
    g = torch.Generator().manual_seed(0)
    n = 50
    o = torch.randn(n, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    t_near = torch.rand(n, generator=g)
    t_far = t_near + 3 * torch.rand(n, generator=g)
    ts, te, ri = march(o, d, t_near, t_far, None, 0.05, 20, jitter=True)
    assert int(torch.bincount(ri, minlength=n).max()) <= 20
    assert bool((ri[1:] >= ri[:-1]).all())
    assert bool((ts >= t_near[ri]).all() and (te <= t_far[ri] + 1e-6).all() and (te > ts).all())


def test_march_cone_angle_steps_grow_geometrically() -> None:
    o, d = torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]])
    ts, te, _ = march(o, d, torch.tensor([0.5]), torch.tensor([100.0]), None, 0.01, 10000, cone_angle=0.01)
    torch.testing.assert_close(ts[1:], te[:-1])
    dt = te - ts
    assert abs(float(dt[0]) - 0.01) < 1e-6  # uniform before t = step / cone = 1
    far = ts > 2.0
    torch.testing.assert_close(dt[far][:-1] / ts[far][:-1], torch.full_like(dt[far][:-1], 0.01), rtol=1e-3, atol=1e-6)
    assert abs(float(te[-1]) - 100.0) < 1e-3


def test_march_early_termination_drops_samples_behind_a_wall() -> None:
    o, d = torch.zeros(2, 3), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    t_near, t_far = torch.zeros(2), torch.full((2,), 2.0)

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        wall = torch.where(ri == 0, 1.0, 10.0)  # ray 0 hits its wall at t = 1, ray 1 never
        return torch.where(0.5 * (ts + te) > wall, torch.full_like(ts, 1e4), torch.zeros_like(ts))

    ts, te, ri = march(o, d, t_near, t_far, None, 0.1, 100, sigma_fn=sigma_fn, min_transmittance=1e-4)
    assert int((ri == 1).sum()) == 20  # transparent ray keeps everything
    kept0 = ts[ri == 0]
    assert float(kept0.max()) == pytest.approx(1.0, abs=1e-5)  # the first opaque sample, nothing behind


def test_contracted_grid_covers_far_points() -> None:
    occ = OccupancyGrid(AABB, resolution=8, sigma_threshold=1.0, warmup_steps=0, contraction=True)
    occ.update(lambda x: (x.norm(dim=-1) > 50).to(x.dtype) * 10, step=0)
    assert bool(occ.query(torch.tensor([[1000.0, 0.0, 0.0]]))[0])
    assert not bool(occ.query(torch.tensor([[0.1, 0.0, 0.0]]))[0])


def test_core_aabb_leaves_out_scattered_floaters() -> None:
    occ = OccupancyGrid(AABB, resolution=32, sigma_threshold=1.0, warmup_steps=0)
    occ.occupied.fill_(False)
    occ.occupied[10:20, 8:22, 12:18] = True  # the object
    occ.occupied[20, 15, 15] = True  # a thin part touching it stays
    occ.occupied[31, 1, 2] = True  # isolated floaters go
    occ.occupied[0, 31, 31] = True
    size = (AABB[1] - AABB[0]) / 32
    expected = torch.stack([AABB[0] + size * torch.tensor([10, 8, 12]), AABB[0] + size * torch.tensor([21, 22, 18])])
    torch.testing.assert_close(occ.core_aabb(), expected)
    assert occ.occupied_aabb()[1, 0] == AABB[1, 0]  # the plain box still reaches the floaters
