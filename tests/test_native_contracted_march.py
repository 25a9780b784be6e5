"""The native marcher on unbounded (contracted) fields against the torch reference: contracted_intervals' steps, the
occupancy grid over the contracted cube and the transmittance cut (recon.nerf.occupancy.march(contracted=True))."""
from __future__ import annotations

import pytest
import torch

import recon.nerf.native as native
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.occupancy import march
from recon.nerf.rays import camera_rays

needs_native = pytest.mark.skipif(native.native_marcher() is None, reason=f"native marcher {native.native_status()}")


def _room_model(levels: int = 3, activation: str = "softplus") -> FastModel:
    """An unbounded fast model holding a noisy opaque ball (radius 0.6, inside the unit box) in front of a wall at
    contracted z = -1.5 (world z = -2, in the contracted shell); occupancy refreshed."""
    torch.manual_seed(0)
    cfg = FastConfig(aabb=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), unbounded=True, density_res=48, feature_res=24,
                     density_levels=levels, occupancy_res=32, density_activation=activation)
    model = FastModel(cfg)
    with torch.no_grad():
        grids = model.density_grid.grids if levels > 1 else [model.density_grid]
        for grid in grids:
            lin = torch.linspace(-2.0, 2.0, grid.res)
            x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
            ball, wall = 40.0 * (0.6 - (x**2 + y**2 + z**2).sqrt()), 40.0 * (0.15 - (z + 1.5).abs())
            grid.table.copy_((torch.maximum(ball, wall) / len(grids) + 0.3 * torch.randn_like(x)).reshape(-1, 1))
        model.color_grid.table.normal_()
    model.occupancy.warmup_steps = 0
    model.occupancy.update(model.density, 100)
    return model.eval()


def _rays(n_side: int = 40) -> tuple[torch.Tensor, ...]:
    """A camera at (0.3, -0.2, 3) looking down -z (rays through the ball, past it onto the wall, and out of the
    room), plus rays along the axes (zero direction components), one empty (far < near) and one from inside."""
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 3.0])
    o, d = camera_rays(c2w, 45.0, 45.0, n_side / 2, n_side / 2, n_side, n_side)
    extra_o = torch.tensor([[0.0, 0.0, 3.0], [5.0, 0.1, -1.0], [0.2, 0.3, 0.1], [0.0, 0.0, 3.0]])
    extra_d = torch.tensor([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    o, d = torch.cat([o.reshape(-1, 3), extra_o]), torch.cat([d.reshape(-1, 3), extra_d])
    tn = torch.full((o.shape[0],), 0.3)
    tf = torch.full((o.shape[0],), 30.0)
    tf[-1] = 0.2  # far before near: no samples
    return o, d, tn, tf


@needs_native
@pytest.mark.parametrize("levels,activation,jitter,max_samples", [(3, "softplus", False, 1024),
                                                                  (1, "trunc_exp", False, 1024),
                                                                  (3, "softplus", True, 1024),
                                                                  (3, "softplus", True, 40)])  # capped: longer steps
def test_native_contracted_march_keeps_the_torch_marchers_samples(levels: int, activation: str, jitter: bool,
                                                                  max_samples: int) -> None:
    model = _room_model(levels, activation)
    assert 0.05 < model.occupancy.occupied_fraction() < 0.5  # culling matters
    o, d, tn, tf = _rays()

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model._sigma_unit(model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0))

    torch.manual_seed(3)
    with torch.no_grad():
        ts, te, ri = march(o, d, tn, tf, model.occupancy, model.step_size, max_samples, jitter=jitter, contracted=True,
                           sigma_fn=sigma_fn, min_transmittance=1e-3)
        ref = (ts, te, ri, sigma_fn(ts, te, ri))
    torch.manual_seed(3)
    field = model._dense_density()
    assert field is not None and field.contracted
    with torch.no_grad():
        got = native.march_dense_native(o, d, tn, tf, jitter, field, model.step_size, max_samples, 1e-3)
    assert got is not None
    hits = torch.bincount(ref[2], minlength=o.shape[0])
    assert int((hits > 0).sum()) > o.shape[0] // 2 and int(hits[-1]) == 0
    assert torch.equal(got[2], ref[2])  # the same samples of the same rays, in the same order
    for a, b in zip(got[:2], ref[:2]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(got[3], ref[3], atol=1e-3, rtol=1e-4)
    torch.manual_seed(3)  # the jitter is drawn as the torch marcher draws it: the same draw, the same steps
    again = native.march_dense_native(o, d, tn, tf, jitter, field, model.step_size, max_samples, 1e-3)
    assert torch.equal(again[0], got[0])


@needs_native
def test_native_contracted_render_equals_the_torch_render_with_fewer_density_evaluations() -> None:
    model = _room_model()
    o, d, tn, tf = _rays(48)
    with torch.inference_mode():
        fast = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    from recon.app.profiling import reference_marching

    with torch.inference_mode(), reference_marching():
        ref = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    assert float(ref["opacity"].max()) > 0.99
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(fast[key], ref[key], atol=1e-4, rtol=1e-4)
    assert fast["num_samples"] == ref["num_samples"]
    # the torch path evaluates every occupied candidate, then the kept ones again; the native march stops at the
    # surface and its densities are the rendered ones
    assert fast["density_evals"] < 0.6 * ref["density_evals"]


@needs_native
def test_an_unbounded_model_trains_on_the_native_samples() -> None:
    """Training marches natively and takes the march's densities for its loss (no second pass over the levels); the
    field gets gradients through the C grid reads."""
    model = _room_model().train()
    o, d, tn, tf = _rays(24)
    torch.manual_seed(5)
    out = model.render_rays(o, d, tn, tf, training=True, background=torch.ones(3))
    assert out["density_evals"] == out["num_samples"]  # the marcher's densities, differentiable
    out["rgb"].sum().backward()
    grads = [g.table.grad for g in model.density_grid.grids]
    assert all(g is not None and float(g.abs().sum()) > 0 for g in grads)
    with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
        mp.setattr("recon.nerf.fast.march_dense_native", lambda *args, **kwargs: None)  # the torch marcher
        torch.manual_seed(5)
        ref = model.render_rays(o, d, tn, tf, training=True, background=torch.ones(3))
    assert ref["num_samples"] == out["num_samples"]
    assert ref["density_evals"] > out["density_evals"]
