"""Training at the extremes: learning rates 10x off the default, NaN appearing mid-run, and a collapsed run.

Complements tests/test_trainer.py (which covers lr=inf at step 1 and bf16 autocast)."""
from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from recon.nerf.fitting import RayBatcher
from recon.nerf.render import RadianceModel
from recon.nerf.trainer import TrainingDiverged, train
from tests.ball_scene import AABB, ball_views, tiny_model

DEFAULT_LR = 5e-4  # the classic model's default (recon/stages/train.py: model_spec)


@pytest.mark.parametrize("factor", [0.1, 10.0])
def test_learning_rate_10x_off_the_default_stays_finite(factor: float) -> None:
    images, c2w, intr = ball_views(4, 12)
    model = tiny_model()
    out = train(model, RayBatcher(images, c2w, intr, aabb=AABB, seed=0), steps=40, lr=DEFAULT_LR * factor,
                batch_rays=128, history_every=10)
    assert math.isfinite(out["loss"]) and math.isfinite(out["psnr"])
    assert all(torch.isfinite(p).all() for p in model.parameters())


class NaNAt(RadianceModel):
    """Wraps a model and makes its density NaN from step `bad_step` on (a blown-up layer, mid-run)."""

    def __init__(self, inner: RadianceModel, bad_step: int) -> None:
        super().__init__()
        self.inner, self.bad_step, self.step = inner, bad_step, 0

    def step_update(self, step: int) -> None:
        self.step = step

    def density(self, x: Tensor) -> Tensor:
        return self.inner.density(x)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return self.inner.radiance(x, d)

    def render_rays(self, rays_o, rays_d, near, far, *, training, background, colors=True):
        out = self.inner.render_rays(rays_o, rays_d, near, far, training=training, background=background)
        if self.step >= self.bad_step:
            out = {**out, "rgb": out["rgb"] * torch.nan}
        return out


def test_nan_mid_run_stops_at_that_step_naming_the_cause_and_keeps_the_last_good_state() -> None:
    images, c2w, intr = ball_views(2, 8)
    model = NaNAt(tiny_model(), bad_step=7)
    seen: list[int] = []
    with pytest.raises(TrainingDiverged) as info:
        train(model, RayBatcher(images, c2w, intr, aabb=AABB), steps=20, lr=1e-3, batch_rays=32,
              callbacks=[lambda p: seen.append(p.step)])
    err = info.value
    assert err.step == 7 and "step 7" in str(err)
    assert "NaN" in err.cause and "rgb" in err.cause and "rendered colors contain NaN" in err.cause
    assert seen == list(range(1, 8))  # the callbacks (checkpointing) saw every good step and no bad one
    assert all(torch.isfinite(p).all() for p in model.parameters())  # the bad step never reached the optimizer


def test_learning_rate_far_too_high_is_reported_not_silent() -> None:
    images, c2w, intr = ball_views(4, 12)
    with pytest.warns(UserWarning, match="learning rate"):
        train(tiny_model(), RayBatcher(images, c2w, intr, aabb=AABB, seed=0), steps=40, lr=DEFAULT_LR * 1000,
              batch_rays=128, history_every=10)
