"""The fast model's front-to-back marching (densities reused when rendering without gradients) renders what
the previous marching rendered, with fewer density evaluations."""
from __future__ import annotations

import pytest
import torch

from recon.app.profiling import reference_marching
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.native import native_marcher
from recon.nerf.occupancy import march, march_front_to_back
from recon.nerf.rays import camera_rays


def _blob_model(unbounded: bool = False, cone_angle: float = 0.0) -> FastModel:
    """A fast model holding an opaque, noisy ball of radius ~0.6 with random colors; occupancy refreshed."""
    torch.manual_seed(0)
    cfg = FastConfig(aabb=((-1.0,) * 3, (1.0,) * 3), density_res=40, feature_res=24, density_levels=1,
                     occupancy_res=20, color_model="mlp_view", unbounded=unbounded, cone_angle=cone_angle,
                     unbounded_steps="world")  # the contracted marcher has no front-to-back variant
    model = FastModel(cfg)
    with torch.no_grad():
        r = model.density_grid.res
        lin = torch.linspace(-1.0, 1.0, r) * (2.0 if unbounded else 1.0)
        x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
        raw = 40.0 * (0.6 - (x**2 + y**2 + z**2).sqrt()) + 0.5 * torch.randn_like(x)
        model.density_grid.table.copy_(raw.reshape(-1, 1))
        model.color_grid.table.normal_()
    model.occupancy.warmup_steps = 0
    model.occupancy.update(model.density, 100)
    return model.eval()


def _rays(n_side: int = 48) -> tuple[torch.Tensor, ...]:
    c2w = torch.eye(4)
    c2w[2, 3] = 3.0
    o, d = camera_rays(c2w, 50.0, 50.0, n_side / 2, n_side / 2, n_side, n_side)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    return o, d, torch.full((o.shape[0],), 1.0), torch.full((o.shape[0],), 5.0)


@pytest.mark.parametrize("unbounded,cone", [(False, 0.0), (True, 1 / 64)])
def test_inference_render_matches_reference_with_fewer_density_evaluations(unbounded: bool, cone: float) -> None:
    model = _blob_model(unbounded, cone)
    o, d, near, far = _rays()
    with torch.no_grad(), reference_marching():  # every occupied candidate's density, then the kept ones' again
        ref = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
    with torch.no_grad():
        fast = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
    with torch.enable_grad():  # with gradients: the same samples, their densities differentiable
        grad = model.render_rays(o, d, near, far, training=False, background=torch.ones(3))
    assert float(ref["opacity"].max()) > 0.99  # some rays end on the ball: early termination matters
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(fast[key], ref[key], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(grad[key].detach(), ref[key], atol=1e-5, rtol=1e-5)
    assert fast["num_samples"] == ref["num_samples"] == grad["num_samples"]
    assert fast["density_evals"] < 0.75 * ref["density_evals"]
    # the C march's densities are the differentiable ones; the torch marchers' are evaluated again
    marched_in_c = model._dense_density() is not None and native_marcher() is not None
    assert grad["density_evals"] == fast["density_evals"] + (0 if marched_in_c else fast["num_samples"])


def test_front_to_back_keeps_the_samples_march_keeps() -> None:
    model = _blob_model()
    o, d, near, far = _rays(32)

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model.density(o[ri] + d[ri] * (0.5 * (ts + te))[:, None])

    args = (o, d, near, far, model.occupancy, model.step_size, 1024)
    ts, te, ri = march(*args, sigma_fn=sigma_fn, min_transmittance=1e-3)
    ts2, te2, ri2, sigma2 = march_front_to_back(*args, sigma_fn, min_transmittance=1e-3, first_window=4, max_window=16)
    assert torch.equal(ri2, ri)
    torch.testing.assert_close(ts2, ts)
    torch.testing.assert_close(te2, te)
    torch.testing.assert_close(sigma2, sigma_fn(ts, te, ri))


def test_training_marches_the_same_samples_with_the_same_jitter() -> None:
    model = _blob_model()
    model.train()
    o, d, near, far = _rays(24)
    torch.manual_seed(5)
    with reference_marching():
        ref = model.render_rays(o, d, near, far, training=True, background=torch.ones(3))
    torch.manual_seed(5)
    new = model.render_rays(o, d, near, far, training=True, background=torch.ones(3))
    assert new["num_samples"] == ref["num_samples"]
    assert new["density_evals"] < ref["density_evals"]
    torch.testing.assert_close(new["rgb"], ref["rgb"], atol=1e-5, rtol=1e-5)
    new["rgb"].sum().backward()  # the kept samples' densities are differentiable
    assert model.density_grid.table.grad is not None and bool(model.density_grid.table.grad.abs().sum() > 0)
