"""The pieces of a training step (recon.nerf.pieces) one by one, and how the trainer calls them: hooks in order,
terms summed in the pieces' order, the step callable on its own giving what train() gives."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from recon.camera import look_at
from recon.nerf.appearance import PhotoAppearance
from recon.nerf.fitting import RayBatcher
from recon.nerf.pieces import Appearance, DepthPriorLoss, EmptyRays, PoseRefine, StepInfo, TrainPiece
from recon.nerf.pose_refine import PoseRefinement
from recon.nerf.render import RadianceModel, render_dense
from recon.nerf.sampling import stratified
from recon.nerf.trainer import TrainStep, train
from tests.ball_scene import masked_ball_photos

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
AT = StepInfo(step=0, steps=10, fraction=None, autocast=None)


class Blob(RadianceModel):
    """A learnable constant density and colour: the smallest field the trainer can fit."""

    def __init__(self) -> None:
        super().__init__()
        self.sigma = nn.Parameter(torch.tensor(1.0))
        self.color = nn.Parameter(torch.zeros(3))

    def density(self, x: Tensor) -> Tensor:
        return self.sigma.abs() * (x.norm(dim=-1) < 0.8)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return torch.sigmoid(self.color).expand(*x.shape[:-1], 3)

    def render_rays(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor, *, training: bool,
                    background: Tensor, colors: bool = True) -> dict[str, Tensor]:
        t = stratified(near, far, 8, jitter=training)
        x = rays_o[:, None] + t[..., None] * rays_d[:, None]
        return render_dense(self.density(x), self.radiance(x, rays_d), t, far, background)


def _batcher(seed: int = 0) -> RayBatcher:
    c2w = torch.tensor(np.stack([look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.5]), np.zeros(3))
                                 for a in (0.0, 2.0, 4.0)]), dtype=torch.float32)
    images = torch.rand(3, 8, 8, 3, generator=torch.Generator().manual_seed(1))
    return RayBatcher(images, c2w, torch.tensor([[8.0, 8.0, 4.0, 4.0]] * 3), aabb=AABB, seed=seed)


def test_empty_rays_cost_their_mean_opacity_and_nothing_without_masks_or_weight() -> None:
    out = {"opacity": torch.tensor([0.5, 0.2, 1.0, 0.0])}
    batch = {"empty": torch.tensor([1.0, 0.0, 1.0, 0.0])}
    terms = EmptyRays(0.1).loss_terms(Blob(), out, batch, AT)
    assert set(terms) == {"empty"}
    torch.testing.assert_close(terms["empty"], torch.tensor(0.1 * 1.5 / 4))
    assert EmptyRays(0.1).loss_terms(Blob(), out, {}, AT) == {}
    assert EmptyRays(0.0).loss_terms(Blob(), out, batch, AT) == {}


@pytest.mark.parametrize("autocast", [None, torch.bfloat16])
def test_depth_prior_loss_calls_the_prior_at_the_step_under_the_steps_autocast(autocast: torch.dtype | None) -> None:
    seen = []

    def prior(model: RadianceModel, step: int) -> dict[str, Tensor]:
        seen.append((step, torch.is_autocast_enabled("cpu")))
        return {"depth": torch.tensor(0.25, dtype=torch.bfloat16)}

    at = StepInfo(step=7, steps=10, fraction=None, autocast=autocast)
    terms = DepthPriorLoss(prior).loss_terms(Blob(), {}, {"rgb": torch.zeros(2, 3)}, at)
    assert seen == [(7, autocast is not None)]
    assert terms["depth"].dtype == torch.float32 and float(terms["depth"]) == 0.25


def test_appearance_joins_the_fields_optimizer_transforms_the_render_and_keeps_its_state() -> None:
    module = PhotoAppearance(3)
    piece = Appearance(module)
    opt = torch.optim.Adam([nn.Parameter(torch.zeros(2))], lr=0.1)
    piece.attach(opt, 0.1)
    assert opt.param_groups[-1]["params"] == list(module.parameters())
    assert opt.param_groups[-1]["lr"] == opt.param_groups[-1]["initial_lr"] == 0.1
    with torch.no_grad():
        module.bias[2] = torch.tensor([0.1, 0.2, 0.3])
    out = {"rgb": torch.full((2, 3), 0.5), "depth": torch.ones(2)}
    changed = piece.after_render(out, {"image": torch.tensor([0, 2])})
    torch.testing.assert_close(changed["rgb"], torch.tensor([[0.5, 0.5, 0.5], [0.6, 0.7, 0.8]]))
    assert changed["depth"] is out["depth"] and torch.equal(out["rgb"], torch.full((2, 3), 0.5))
    assert float(piece.loss_terms(Blob(), changed, {}, AT)["appearance"].detach()) == float(module.regularizer().detach()) > 0
    fresh = Appearance(PhotoAppearance(3))
    fresh.load_state_dict(piece.state_dict())
    assert torch.equal(fresh.module.bias, module.bias)


def test_pose_refine_learns_only_on_its_steps_with_its_own_optimizer() -> None:
    module = PoseRefinement(3, every=2, start=0.0, lr=1e-2)
    piece = PoseRefine(module, AABB)
    field_opt = torch.optim.Adam([nn.Parameter(torch.zeros(2))], lr=0.1)
    piece.attach(field_opt, 0.1)
    assert len(field_opt.param_groups) == 1  # the field's rate schedule would turn the cameras far too fast
    batch = _batcher().next_batch(16)
    for step, learns in ((1, False), (2, True)):
        at = StepInfo(step=step, steps=10, fraction=None, autocast=None)
        moved = piece.before_render(batch, at)
        assert moved["rays_o"].requires_grad == learns
        terms = piece.loss_terms(Blob(), {}, moved, at)
        assert set(terms) == ({"pose"} if learns else set())
        before = module.translation.detach().clone()
        if learns:
            (moved["rays_o"].sum() + moved["rays_d"].sum() + terms["pose"]).backward()
        piece.after_step(at)
        assert (not torch.equal(module.translation, before)) == learns
    state = piece.state_dict()
    assert set(state) == {"pose_refine", "pose_optimizer"} and state["pose_optimizer"]["state"]
    fresh = PoseRefine(PoseRefinement(3, every=2, start=0.0, lr=1e-2), AABB)
    fresh.attach(field_opt, 0.1)
    fresh.load_state_dict(state)
    assert torch.equal(fresh.module.rotation, module.rotation)


class Recorder(TrainPiece):
    """Adds a constant term and records the hooks the trainer calls."""

    def __init__(self, name: str, value: float, log: list[str]) -> None:
        self.name, self.value, self.log = name, value, log

    def attach(self, opt: torch.optim.Optimizer, lr: float) -> None:
        self.log.append(f"{self.name}.attach")

    def before_render(self, batch: dict[str, Tensor], at: StepInfo) -> dict[str, Tensor]:
        self.log.append(f"{self.name}.before_render")
        return batch

    def after_render(self, out: dict, batch: dict[str, Tensor]) -> dict:
        self.log.append(f"{self.name}.after_render")
        return out

    def loss_terms(self, model: RadianceModel, out: dict, batch: dict[str, Tensor], at: StepInfo) -> dict[str, Tensor]:
        self.log.append(f"{self.name}.loss_terms")
        return {self.name: torch.tensor(self.value)}

    def after_step(self, at: StepInfo) -> None:
        self.log.append(f"{self.name}.after_step")


def test_the_trainer_calls_each_hook_piece_by_piece_and_adds_their_terms_in_order() -> None:
    log: list[str] = []
    torch.manual_seed(0)
    plain = train(Blob(), _batcher(), steps=1, lr=1e-2, batch_rays=32)["loss"]
    torch.manual_seed(0)
    loss = train(Blob(), _batcher(), steps=1, lr=1e-2, batch_rays=32,
                 pieces=[Recorder("a", 0.5, log), Recorder("b", 0.25, log)])["loss"]
    assert log == ["a.attach", "b.attach", "a.before_render", "b.before_render", "a.after_render", "b.after_render",
                   "a.loss_terms", "b.loss_terms", "a.after_step", "b.after_step"]
    assert loss == pytest.approx(plain + 0.75, abs=1e-6)


def test_the_step_taken_on_its_own_is_the_step_train_takes() -> None:
    torch.manual_seed(0)
    looped = Blob()
    train(looped, _batcher(), steps=5, lr=1e-2, batch_rays=32, pieces=[EmptyRays(0.1)])
    torch.manual_seed(0)
    stepped = Blob()
    take = TrainStep(stepped, _batcher(), steps=5, lr=1e-2, batch_rays=32, pieces=[EmptyRays(0.1)])
    results = [take(step) for step in range(5)]
    assert all(torch.equal(a, b) for a, b in zip(looped.parameters(), stepped.parameters(), strict=True))
    assert results[0].lr == 1e-2 and "rgb" in results[-1].out


def test_masked_photos_transparent_pixels_trained_as_empty_space_leave_less_haze_than_random_backgrounds_alone() -> None:
    """What `train.transparent_weight` is for: on random backgrounds alone the field keeps a faint haze where the
    masks say nothing is; the empty-space term clears most of it, and the object stays opaque."""
    from recon.nerf.fast import FastConfig, FastModel

    images, c2w, intr = masked_ball_photos()
    images = [torch.from_numpy(im) for im in images]
    empty = [im[..., 3] == 0 for im in images]
    haze, solid = {}, {}
    for weight in (0.0, 0.1):
        torch.manual_seed(0)
        model = FastModel(FastConfig(aabb=AABB.tolist(), density_res=24, feature_res=16, feature_dim=4, occupancy_res=8,
                                     occupancy_warmup=4, occupancy_every=2, mlp_width=16, mlp_layers=1))
        batcher = RayBatcher(images, c2w, intr, aabb=AABB, random_background=True, empty=empty if weight else None, seed=0)
        train(model, batcher, steps=150, lr=2e-2, batch_rays=256, pieces=[EmptyRays(weight)] if weight else [])
        model.eval()
        batch = RayBatcher(images, c2w, intr, aabb=AABB, empty=empty, seed=5).next_batch(4096)
        with torch.no_grad():
            out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"], training=False,
                                    background=torch.ones(3))
        known_empty = batch["empty"] > 0
        haze[weight] = float(out["opacity"][known_empty].mean())
        solid[weight] = float(out["opacity"][~known_empty].mean())
    assert haze[0.1] < haze[0.0] / 4, haze
    assert min(solid.values()) > 0.95, solid
