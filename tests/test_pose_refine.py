"""Per-photo pose refinement: the rotation map, corrected rays, recovering a camera turned off its true pose
with the field held exact, resuming, and the automatic choice."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from recon.camera import look_at
from recon.config import TrainConfig
from recon.nerf.evaluate import align_pose, render_image
from recon.nerf.fitting import RayBatcher
from recon.nerf.pieces import PoseRefine
from recon.nerf.pose_refine import PoseRefinement, so3_exp
from recon.nerf.render import RadianceModel, render_dense
from recon.nerf.sampling import stratified
from recon.nerf.trainer import train
from recon.plans.training import choose_pose_refine

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _skew(r: Tensor) -> Tensor:
    k = torch.zeros(r.shape[0], 3, 3, dtype=r.dtype)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    return k - k.transpose(1, 2)


def test_so3_exp_is_the_matrix_exponential_with_finite_gradients_at_the_extremes() -> None:
    r = torch.cat([torch.randn(6, 3, dtype=torch.float64), torch.tensor([[0.0, 0.0, 0.0], [1e-9, 0, 0], [3.0, 0, 0]],
                                                                          dtype=torch.float64)])
    rot = so3_exp(r)
    torch.testing.assert_close(rot, torch.linalg.matrix_exp(_skew(r)), atol=1e-12, rtol=0)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(9, 3, 3))
    for start in (torch.zeros(1, 3), torch.full((1, 3), 1e-7), torch.full((1, 3), 2.0)):
        x = start.clone().requires_grad_(True)
        so3_exp(x)[0, 0, 1].backward()  # d R01 / d r2 = -1 at zero
        assert torch.isfinite(x.grad).all()
    z = torch.zeros(1, 3, requires_grad=True)
    so3_exp(z)[0, 0, 1].backward()
    torch.testing.assert_close(z.grad, torch.tensor([[0.0, 0.0, -1.0]]))


def test_corrections_turn_and_shift_only_their_own_photos_rays() -> None:
    refine = PoseRefinement(2)
    o, d = torch.tensor([[0.0, 0.0, 3.0]] * 2), torch.tensor([[0.0, 0.0, -1.0]] * 2)
    batch = {"rays_o": o, "rays_d": d, "image": torch.tensor([0, 1]), "near": torch.ones(2), "far": torch.full((2,), 5.0)}
    same = refine.correct_batch(batch, AABB)
    assert torch.equal(same["rays_o"], o) and torch.equal(same["rays_d"], d)
    assert float(refine.regularizer().detach()) == 0.0
    with torch.no_grad():
        refine.rotation[1] = torch.tensor([0.0, math.radians(10.0), 0.0])
        refine.translation[1] = torch.tensor([0.1, 0.0, 0.0])
    out = refine.correct_batch(batch, AABB)
    torch.testing.assert_close(out["rays_o"][0], o[0])
    torch.testing.assert_close(out["rays_d"][0], d[0])
    torch.testing.assert_close(out["rays_o"][1], torch.tensor([0.1, 0.0, 3.0]))
    turned = torch.tensor([-math.sin(math.radians(10.0)), 0.0, -math.cos(math.radians(10.0))])
    torch.testing.assert_close(out["rays_d"][1], turned)
    # near/far re-cut against the box along the turned ray: it enters the z = 1 face
    assert abs(float(out["near"][1]) - 2.0 / math.cos(math.radians(10.0))) < 1e-5


class TexturedBall(RadianceModel):
    """A soft ball with a smooth colour pattern: the field is exact, so only the cameras are left to learn."""

    def __init__(self) -> None:
        super().__init__()
        self.unused = nn.Parameter(torch.zeros(()))

    def density(self, x: Tensor) -> Tensor:
        return 40.0 * torch.sigmoid((0.6 - x.norm(dim=-1)) * 30.0)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return 0.5 + 0.4 * torch.stack([torch.sin(6 * x[..., 0]), torch.sin(6 * x[..., 1] + 1), torch.cos(6 * x[..., 2])], -1)

    def render_rays(self, rays_o, rays_d, near, far, *, training, background, colors=True):
        t = stratified(near, far, 64, jitter=False)
        x = rays_o[:, None] + t[..., None] * rays_d[:, None]
        out = render_dense(self.density(x), self.radiance(x, rays_d) + 0.0 * self.unused, t, far, background)
        out["background"] = torch.as_tensor(background).expand(rays_o.shape[0], 3)
        return out


def _capture(n: int = 4, size: int = 16) -> tuple[Tensor, Tensor, Tensor]:
    c2w = torch.tensor(np.stack([look_at(np.array([3 * math.cos(a), 3 * math.sin(a), 0.8]), np.zeros(3))
                                 for a in np.arange(n) * 2 * math.pi / n]), dtype=torch.float32)
    intr = torch.tensor([[size * 1.2, size * 1.2, size / 2, size / 2]]).expand(n, 4).contiguous()
    images = torch.stack([render_image(TexturedBall(), c, intr[0], size, size, aabb=AABB)["rgb"] for c in c2w])
    return images, c2w, intr


def test_training_turns_a_misplaced_camera_back_and_leaves_the_right_ones() -> None:
    """Photo 1's camera is given 1.5° off its true pose (the photo is the true view): the corrections must undo most
    of the turn, and the three right cameras must stay where they are."""
    images, c2w, intr = _capture()
    off = torch.tensor([0.0, math.radians(1.5), math.radians(0.8)])
    given = c2w.clone()
    given[1, :3, :3] = so3_exp(off[None])[0] @ c2w[1, :3, :3]
    refine = PoseRefinement(4, centres=given[:, :3, 3], lr=4e-3, every=1, start=0.0)
    batcher = RayBatcher(images, given, intr, aabb=AABB, seed=0)
    before = train(TexturedBall(), batcher, steps=1, lr=1e-3, batch_rays=512)["loss"]
    after = train(TexturedBall(), RayBatcher(images, given, intr, aabb=AABB, seed=0), steps=250, lr=1e-3,
                  batch_rays=512, pieces=[PoseRefine(refine, AABB)])["loss"]
    corrected = refine.corrected_c2w(given.double())[1]
    was, now = _pixel_error(given[1], c2w[1], intr[0]), _pixel_error(corrected, c2w[1], intr[0])
    assert now < 0.2 * was, f"ball points {now:.3f} px off after, {was:.3f} px before"
    others = torch.cat([refine.rotation[[0, 2, 3]].norm(dim=-1), refine.translation[[0, 2, 3]].norm(dim=-1)])
    assert float(others.detach().max()) < math.radians(0.2)
    assert after < 0.2 * before


def _pixel_error(c2w: Tensor, true_c2w: Tensor, intr: Tensor) -> float:
    """Mean distance (pixels) between where camera c2w and the true camera put points on the ball's surface."""
    g = torch.Generator().manual_seed(0)
    points = torch.randn(500, 3, generator=g, dtype=torch.float64)
    points = 0.6 * points / points.norm(dim=-1, keepdim=True)

    def project(m: Tensor) -> Tensor:
        m = m.double()
        cam = (points - m[:3, 3]) @ m[:3, :3]  # OpenGL camera axes: looks down -z
        return torch.stack([intr[0] * cam[:, 0] / -cam[:, 2], intr[1] * cam[:, 1] / -cam[:, 2]], -1)

    return float((project(c2w) - project(true_c2w)).norm(dim=-1).mean())


def test_a_held_out_photo_is_aligned_to_the_frozen_field_from_its_left_half() -> None:
    images, c2w, intr = _capture(1, 24)
    given = c2w[0].clone()
    given[:3, :3] = so3_exp(torch.tensor([[0.0, math.radians(1.2), -math.radians(0.6)]]))[0] @ c2w[0, :3, :3]
    model = TexturedBall()
    before = [p.detach().clone() for p in model.parameters()]
    fitted = align_pose(model, images[0][:, :12], given, intr[0].tolist(), aabb=AABB, steps=150)
    was, now = _pixel_error(given, c2w[0], intr[0]), _pixel_error(fitted, c2w[0], intr[0])
    assert now < 0.2 * was, f"ball points {now:.3f} px off after, {was:.3f} px before"
    assert all(torch.equal(a, b) and b.requires_grad for a, b in zip(before, model.parameters()))


def test_a_resumed_run_refines_as_the_uninterrupted_one() -> None:
    images, c2w, intr = _capture(3, 12)
    # one camera turned 1° off its true pose: at the true poses an exact field's loss has no gradient at all (the run
    # learned only from rounding noise, and on a CPU whose renders match bit for bit nothing moved)
    given = c2w.clone()
    given[1, :3, :3] = so3_exp(torch.tensor([[0.0, math.radians(1.0), 0.0]]))[0] @ c2w[1, :3, :3]
    full = PoseRefinement(3, lr=1e-3, every=2, start=0.0)
    train(TexturedBall(), RayBatcher(images, given, intr, aabb=AABB, seed=0), steps=12, lr=1e-3, batch_rays=128,
          pieces=[PoseRefine(full, AABB)])
    first = PoseRefinement(3, lr=1e-3, every=2, start=0.0)
    states = []
    train(TexturedBall(), RayBatcher(images, given, intr, aabb=AABB, seed=0), steps=12, lr=1e-3, batch_rays=128,
          pieces=[PoseRefine(first, AABB)], callbacks=[lambda p: states.append(p.state_fn()) if p.step == 5 else None])
    resumed = PoseRefinement(3, lr=1e-3, every=2, start=0.0)
    train(TexturedBall(), RayBatcher(images, given, intr, aabb=AABB, seed=0), steps=12, lr=1e-3, batch_rays=128,
          pieces=[PoseRefine(resumed, AABB)], state=states[0])
    assert float(full.rotation.detach().abs().max()) > 0.0
    torch.testing.assert_close(resumed.rotation, full.rotation)
    torch.testing.assert_close(resumed.translation, full.translation)


def test_it_waits_for_the_field_and_learns_every_nth_step() -> None:
    refine = PoseRefinement(1, every=4, start=0.1)
    assert [s for s in range(40) if refine.learns_at(s, 40)] == [4, 8, 12, 16, 20, 24, 28, 32, 36]
    assert refine.learns_at(0, 1000, fraction=0.5) and not refine.learns_at(0, 1000, fraction=0.05)


@pytest.mark.parametrize(("setting", "kind", "on"), [("off", "fast", False), ("on", "fast", True),
                                                    ("on", "surface", True), ("on", "classic", False)])
def test_refinement_is_chosen_as_configured_and_says_why(setting: str, kind: str, on: bool) -> None:
    chosen, why = choose_pose_refine(TrainConfig(pose_refine=setting), kind)
    assert chosen is on
    assert why.startswith(f"pose refinement {'on' if on else 'off'}")
