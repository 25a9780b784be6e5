"""Grid encodings: fast paths against plain references, closed forms, and in-range indices at the box faces."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from recon.nerf.grid import (
    DenseGrid,
    HashGrid,
    VMGrid,
    axis_cells,
    corner_rows,
    corner_weights,
    gather_interp,
    hash_reference,
    trilinear_reference,
)


def _points(m: int, seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    """Random points in [0, 1]^3 plus the 8 box corners and points on every face."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(m, 3, generator=g, dtype=dtype)
    corners = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=dtype)
    faces = torch.rand(6, 3, generator=g, dtype=dtype)
    for i in range(6):
        faces[i, i % 3] = float(i // 3)
    return torch.cat([x, corners, faces])


@pytest.mark.parametrize("channels", [1, 5])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_grid_matches_reference(channels: int, dtype: torch.dtype) -> None:
    grid = DenseGrid(7, channels, init_std=1.0).to(dtype)
    x = _points(200, dtype=dtype)
    ref = trilinear_reference(grid.volume().detach(), x)
    out = grid(x)
    assert out.dtype == dtype
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)


def test_dense_grid_matches_grid_sample() -> None:
    """Independent check of the index layout: torch's grid_sample on the (C, ix, iy, iz) volume."""
    grid = DenseGrid(6, 3, init_std=1.0)
    x = _points(100)
    vol = grid.volume().detach().permute(3, 0, 1, 2)[None]  # (1, C, D=ix, H=iy, W=iz)
    ref = F.grid_sample(vol, (x * 2 - 1).flip(-1).view(1, 1, 1, -1, 3), align_corners=True).view(3, -1).t()
    torch.testing.assert_close(grid(x), ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("channels", [1, 4])
def test_trilinear_reproduces_affine_functions(channels: int) -> None:
    """Closed form: trilinear interpolation of an affine function of the vertex position is exact."""
    res = 9
    grid = DenseGrid(res, channels)
    lin = torch.linspace(0, 1, res)
    pos = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)  # row-major vertices
    a = torch.arange(1.0, 1.0 + 3 * channels).view(3, channels)
    with torch.no_grad():
        grid.table.copy_(pos @ a + 0.5)
    x = _points(300)
    torch.testing.assert_close(grid(x), x @ a + 0.5, rtol=1e-5, atol=1e-5)


def test_gather_backward_matches_autograd_reference() -> None:
    grid = DenseGrid(5, 3, init_std=1.0).double()
    x = _points(50, dtype=torch.float64)
    g_out = torch.randn(x.shape[0], 3, dtype=torch.float64)
    (grid(x) * g_out).sum().backward()
    vol = grid.volume().detach().clone().requires_grad_(True)
    (trilinear_reference(vol, x) * g_out).sum().backward()
    torch.testing.assert_close(grid.table.grad.view(5, 5, 5, 3), vol.grad)


def test_gather_interp_gradcheck_in_table_and_weights() -> None:
    g = torch.Generator().manual_seed(1)
    table = torch.randn(10, 2, dtype=torch.float64, generator=g, requires_grad=True)
    idx = torch.randint(0, 10, (6, 4), generator=g)
    w = torch.rand(6, 4, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, ww: gather_interp(t, idx, ww), (table, w))


def test_gather_interp_rejects_out_of_range_rows() -> None:
    with pytest.raises(IndexError, match="out of range"):
        gather_interp(torch.zeros(4, 1), torch.tensor([[0, 4]]), torch.ones(1, 2))


def test_corner_rows_and_weights_at_far_corner() -> None:
    """x = 1 on every axis: clamped cell, all weight on the last vertex, no row past the end."""
    i0, frac = axis_cells(torch.ones(1, 3), 4)
    rows, w = corner_rows(i0, 4), corner_weights(frac)
    assert int(rows.max()) == 4**3 - 1
    assert float(w[0, -1]) == 1.0 and float(w.sum()) == 1.0


def test_vm_grid_matches_bilinear_reference() -> None:
    """Each factor against grid_sample (2D planes, 1D lines as 2D with one row)."""
    grid = VMGrid(6, 2, init_std=1.0)
    x = _points(100)
    r, c = 6, 2
    outs = []
    for a, (b, cc) in enumerate(((1, 2), (0, 2), (0, 1))):
        plane = grid.planes[a].detach().view(r, r, c).permute(2, 0, 1)[None]  # (1, C, H=x_b, W=x_c)
        uv = (x[:, (b, cc)] * 2 - 1).flip(-1).view(1, 1, -1, 2)
        p = F.grid_sample(plane, uv, align_corners=True).view(c, -1).t()
        line = grid.lines[a].detach().t()[None, :, :, None]  # (1, C, H=x_a, W=1)
        uv_l = torch.stack([torch.zeros_like(x[:, a]), x[:, a] * 2 - 1], -1).view(1, 1, -1, 2)
        ln = F.grid_sample(line, uv_l, align_corners=True).view(c, -1).t()
        outs.append(p * ln)
    torch.testing.assert_close(grid(x), torch.cat(outs, -1), rtol=1e-5, atol=1e-5)


def test_hash_grid_matches_reference_dense_and_hashed_levels() -> None:
    grid = HashGrid(levels=4, features=2, log2_table=9, base_res=3, max_res=40, init_scale=1.0)
    assert grid.hashed[0] is False and grid.hashed[-1] is True  # covers both storage modes
    x = _points(30, seed=3)
    torch.testing.assert_close(grid(x), hash_reference(grid, x), rtol=1e-5, atol=1e-5)


def test_hash_rows_in_range_at_faces_and_corners() -> None:
    grid = HashGrid(levels=6, features=2, log2_table=10, base_res=4, max_res=2048)
    x = _points(500, seed=4)
    x = torch.cat([x, x.clamp(0, 1) * 0 + 1, x * 0, torch.tensor([[1.0, 1.0, 1.0]]) + 1e-7])
    total = grid.table.shape[0]
    for lv, n in enumerate(grid.verts):
        i0, _ = axis_cells(x, n)
        rows = grid.level_rows(i0, lv)
        lo = int(grid.offsets[lv])
        hi = lo + (2**grid.log2_table if grid.hashed[lv] else n**3)
        assert int(rows.min()) >= lo and int(rows.max()) < hi <= total
    assert torch.isfinite(grid(x)).all()


@pytest.mark.parametrize("make", [lambda: DenseGrid(4, 1), lambda: DenseGrid(4, 3), lambda: VMGrid(4, 2),
                                  lambda: HashGrid(levels=3, log2_table=8, base_res=2, max_res=16)])
def test_empty_batch(make) -> None:
    grid = make()
    out = grid(torch.zeros(0, 3))
    assert out.shape == (0, grid.out_dim)
    out.sum().backward()


def test_multi_dense_grid_is_the_sum_of_its_levels() -> None:
    from recon.nerf.grid import MultiDenseGrid

    grid = MultiDenseGrid(17, 2, levels=3, min_res=4, init_std=1.0)
    assert grid.resolutions == [5, 9, 17]
    x = _points(100)
    ref = sum(trilinear_reference(g.volume().detach(), x) for g in grid.grids)
    torch.testing.assert_close(grid(x), ref, rtol=1e-5, atol=1e-5)


def test_the_memory_check_counts_a_hash_grid_by_its_tables() -> None:
    """A hash grid's memory is its tables' (levels × 2**hash_table_log2 rows at most), not a dense grid of its
    finest resolution: 16 levels up to 1024 fit where a dense 1024³ grid is refused."""
    from recon.config import TRAINING_BYTES_PER_PARAMETER, ConfigError, implied_memory, load_config
    from recon.nerf.fast import FastModel

    hashed = ["train.fast.grid=hash", "train.fast.feature_dim=16", "train.fast.hash_table_log2=19"]
    fine = load_config("fast", [*hashed, "train.fast.feature_res=1024"])  # not refused
    with pytest.raises(ConfigError, match="more than this machine"):
        load_config("fast", ["train.fast.feature_res=1024"])
    small = load_config("fast", [*hashed, "train.fast.feature_res=64", "train.fast.hash_table_log2=12",
                                 "train.fast.density_res=16", "train.fast.density_levels=1"])
    model = FastModel(small.train.fast)
    counted = next(need for keys, _, need in implied_memory(small) if keys.startswith("train.fast"))
    values = sum(p.numel() for grid in (model.density_grid, model.color_grid) for p in grid.parameters())
    assert counted == values * TRAINING_BYTES_PER_PARAMETER
    assert implied_memory(fine)[-1][2] < 2**31
