"""The native marcher and feature gather (recon/nerf/march.c) against the torch paths they replace, and the
fallback to torch when the library cannot be built."""
from __future__ import annotations

import pytest
import torch

import recon.nerf.native as native
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.grid import DenseGrid
from recon.nerf.occupancy import march_front_to_back
from recon.nerf.rays import camera_rays, ray_aabb

needs_native = pytest.mark.skipif(native.native_marcher() is None, reason=f"native marcher {native.native_status()}")


def _ball_model(levels: int, activation: str) -> FastModel:
    """A fast model holding a noisy opaque ball (radius ~0.6) on ``levels`` density grids; occupancy refreshed."""
    torch.manual_seed(0)
    cfg = FastConfig(aabb=((-1.0, -1.2, -0.8), (1.1, 1.0, 1.0)), density_res=40, feature_res=24, density_levels=levels,
                     occupancy_res=20, density_activation=activation)
    model = FastModel(cfg)
    with torch.no_grad():
        grids = model.density_grid.grids if levels > 1 else [model.density_grid]
        for i, grid in enumerate(grids):
            r = grid.res
            lin = torch.linspace(-1.0, 1.0, r)
            x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
            raw = (40.0 if i == 0 else 4.0) * (0.6 - (x**2 + y**2 + z**2).sqrt()) + 0.5 * torch.randn_like(x)
            grid.table.copy_(raw.reshape(-1, 1) / len(grids))
        model.color_grid.table.normal_()
    model.occupancy.warmup_steps = 0
    model.occupancy.update(model.density, 100)
    return model.eval()


def _rays(model: FastModel, n_side: int = 40) -> tuple[torch.Tensor, ...]:
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 3.0])
    o, d = camera_rays(c2w, 45.0, 45.0, n_side / 2, n_side / 2, n_side, n_side)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    tn, tf, hit = ray_aabb(o, d, model.aabb)
    return o, d, tn.clamp_min(0.5), torch.where(hit, tf, tn)


@needs_native
@pytest.mark.parametrize("levels,activation,jitter", [(3, "softplus", False), (1, "trunc_exp", False), (3, "softplus", True)])
def test_native_march_keeps_the_torch_marchers_samples(levels: int, activation: str, jitter: bool) -> None:
    model = _ball_model(levels, activation)
    o, d, tn, tf = _rays(model)

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model._sigma_unit(model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0))

    torch.manual_seed(3)
    ref = march_front_to_back(o, d, tn, tf, model.occupancy, model.step_size, 1024, sigma_fn, jitter=jitter,
                              min_transmittance=1e-3)
    torch.manual_seed(3)
    levels_ = model.density_grid.grids if levels > 1 else [model.density_grid]
    with torch.no_grad():
        got = native.march_dense_native(o, d, tn, tf, jitter, model.occupancy.occupied, model.occupancy.box, model.step_size,
                                        1024, 1e-3, [g.table.view(-1) for g in levels_], model.grid_box,
                                        model.density_bias, model.density_scale, activation == "trunc_exp")
    assert got is not None
    assert ref[2].numel() > 10 * o.shape[0] // 4  # the ball is hit: many samples, early termination matters
    assert torch.equal(got[2], ref[2])  # the same samples of the same rays, in the same order
    for a, b in zip(got[:2], ref[:2]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(got[3], ref[3], atol=1e-3, rtol=1e-4)


@needs_native
def test_native_render_equals_the_torch_render() -> None:
    model = _ball_model(3, "softplus")
    o, d, tn, tf = _rays(model, 48)
    with torch.inference_mode():
        fast = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    from recon.profiling import reference_marching

    with torch.inference_mode(), reference_marching():
        ref = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    assert float(ref["opacity"].max()) > 0.99
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(fast[key], ref[key], atol=1e-4, rtol=1e-4)
    assert fast["num_samples"] == ref["num_samples"]


@needs_native
def test_native_features_equal_the_gather_at_cells_faces_and_corners() -> None:
    torch.manual_seed(1)
    grid = DenseGrid(7, 12, init_std=1.0)
    x = torch.cat([torch.rand(5000, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.0], [1 / 6, 2 / 6, 1.0]]),
                   torch.rand(50, 3) * 1.4 - 0.2])  # beyond the cube too: clamped like the torch path
    with torch.enable_grad():
        ref = grid(x)  # with gradients: the torch gather
    with torch.no_grad():
        got = grid(x)
        direct = native.trilinear_features_native(x, grid.table, grid.res)
    assert direct is not None
    torch.testing.assert_close(got, ref.detach(), atol=1e-5, rtol=1e-5)
    assert torch.equal(got, direct)


def test_a_failed_build_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # nothing built here yet
    monkeypatch.setenv("CC", "false")  # a "compiler" that fails
    native.native_marcher.cache_clear()
    try:
        assert native.native_marcher() is None
        assert native.native_status().startswith("torch: building recon/nerf/march.c failed")
        model = _ball_model(1, "softplus")
        o, d, tn, tf = _rays(model, 16)
        assert native.march_dense_native(o, d, tn, tf, False, model.occupancy.occupied, model.occupancy.box, 0.01, 64, 1e-3,
                                         [model.density_grid.table.view(-1)], model.grid_box, 0.0, 1.0, False) is None
        with torch.no_grad():  # the model renders through the torch marcher
            out = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
        assert out["num_samples"] > 0
        monkeypatch.setenv("RECON_NATIVE", "0")
        native.native_marcher.cache_clear()
        assert native.native_marcher() is None and native.native_status() == "torch (RECON_NATIVE=0)"
    finally:
        native.native_marcher.cache_clear()
