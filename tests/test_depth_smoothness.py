"""The edge-aware depth smoothness (recon/nerf/smoothness.py): zero on any plane, positive on bumps, off across
the photo's edges, patches inside the masks, and a term that flattens a bumpy surface through render_rays."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from recon.camera import look_at
from recon.capture.scene import Frame, Scene
from recon.config import TrainConfig
from recon.evaluation.views import View
from recon.nerf.rays import pixel_rays
from recon.nerf.smoothness import PatchSmoothness, patch_smoothness_loss
from recon.plans.training import build_training, plan_training
from tests.ball_scene import masked_ball_photos

F, W, H = 200.0, 160, 120


def _patch_rays(patches: int, size: int, stride: int, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Rays (P·S·S) of random patches of a camera at the origin looking down -Z, and their pixel x (P, S, S)."""
    gen = torch.Generator().manual_seed(seed)
    span = (size - 1) * stride
    y0 = torch.randint(0, H - span, (patches, 1, 1), generator=gen)
    x0 = torch.randint(0, W - span, (patches, 1, 1), generator=gen)
    offs = torch.arange(size) * stride
    ys = (y0 + offs[None, :, None]).expand(-1, size, size)
    xs = (x0 + offs[None, None, :]).expand(-1, size, size)
    n = patches * size * size
    k = torch.full((n,), F)
    _, d = pixel_rays(torch.eye(4).expand(n, 4, 4), k, k, torch.full((n,), W / 2), torch.full((n,), H / 2),
                      xs.reshape(-1).float() + 0.5, ys.reshape(-1).float() + 0.5)
    return d, -d[:, 2], xs


@pytest.mark.parametrize("normal", [(0.0, 0.0, -1.0), (0.4, -0.3, -1.0), (-0.7, 0.2, -0.5)])
def test_any_plane_costs_nothing_and_a_bump_on_it_costs(normal: tuple[float, float, float]) -> None:
    p, s = 12, 4
    d, cos, xs = _patch_rays(p, s, 8)
    n = torch.tensor(normal) / torch.tensor(normal).norm()
    t = 2.0 / (d @ n)  # distances along the rays to the plane n·x = 2
    plain, seen = torch.zeros(p, s, s), torch.ones(p, s, s)
    flat = patch_smoothness_loss(t.view(p, s, s), cos.view(p, s, s), plain, seen, 10.0)
    bumpy = t.view(p, s, s) * (1.0 + 0.03 * torch.sin(xs.float() / 7.0))
    assert float(flat) < 1e-9
    assert float(patch_smoothness_loss(bumpy, cos.view(p, s, s), plain, seen, 10.0)) > 1e-3


def test_an_edge_in_the_photo_or_a_ray_that_sees_nothing_turns_the_term_off() -> None:
    p, s = 12, 4
    d, cos, xs = _patch_rays(p, s, 8, seed=1)
    bumpy = (2.0 / -d[:, 2]).view(p, s, s) * (1.0 + 0.03 * torch.sin(xs.float() / 7.0))
    plain, seen = torch.zeros(p, s, s), torch.ones(p, s, s)
    base = float(patch_smoothness_loss(bumpy, cos.view(p, s, s), plain, seen, 10.0))
    stripes = ((xs // 8) % 2).float()  # black and white columns: an edge across every horizontal difference
    striped = float(patch_smoothness_loss(bumpy, cos.view(p, s, s), stripes, seen, 10.0))
    empty = float(patch_smoothness_loss(bumpy, cos.view(p, s, s), plain, torch.zeros(p, s, s), 10.0))
    assert striped < 0.6 * base  # the horizontal half is off; the vertical differences of a sin(x) bump are 0
    assert empty == 0.0


def test_patches_of_a_masked_photo_lie_wholly_inside_its_mask_and_repeat_at_the_same_step() -> None:
    rng = np.random.default_rng(0)
    image = np.zeros((H, W, 4), np.uint8)
    image[..., :3] = rng.integers(0, 255, (H, W, 3))
    image[30:100, 20:120, 3] = 255
    image[50:60, 60:70, 3] = 0  # a hole in the mask
    c2w = look_at(np.array([0.0, -3.0, 0.0]), np.zeros(3))[None]
    smooth = PatchSmoothness([image], c2w, np.array([[F, F, W / 2, H / 2]]), 1.0, 64, size=4, stride=5,
                             aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    assert len(smooth) > 0
    span = 3 * 5 + 1
    for _, y, x in smooth.starts.tolist():
        assert image[y:y + span, x:x + span, 3].min() == 255
    assert smooth.starts[:, 1].max() + span <= 100 and smooth.starts[:, 2].min() >= 20


class _BumpyPlane(nn.Module):
    """A 'field' whose surface is the plane y = 0 with a bump of learnable height: render_rays returns the distance
    to it along each ray (opacity 1)."""

    def __init__(self) -> None:
        super().__init__()
        self.height = nn.Parameter(torch.tensor(0.2))

    def render_rays(self, rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor, *, training: bool,
                    background: Tensor | None = None, colors: bool = True) -> dict[str, Tensor]:
        t = -rays_o[:, 1] / rays_d[:, 1]
        hit = rays_o + t[:, None] * rays_d
        bump = self.height * torch.exp(-(hit[:, 0] ** 2 + hit[:, 2] ** 2) / 0.1)
        t = (bump - rays_o[:, 1]) / rays_d[:, 1]  # the ray meets the raised surface about there
        return {"depth": t, "opacity": torch.ones_like(t), "rgb": torch.zeros(len(t), 3)}


def test_the_term_flattens_a_bump_on_a_plain_surface_through_render_rays() -> None:
    image = np.full((H, W, 3), 128, np.uint8)  # plain: the colours cannot place the surface
    c2w = look_at(np.array([0.0, -2.5, 0.3]), np.zeros(3))[None]
    model = _BumpyPlane()
    smooth = PatchSmoothness([image], c2w, np.array([[F, F, W / 2, H / 2]]), 1.0, 64, size=4, stride=6,
                             aabb=torch.tensor([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]]))
    opt = torch.optim.Adam(model.parameters(), lr=0.01)
    first = float(smooth(model, 0)["smooth"].detach())
    for step in range(60):
        opt.zero_grad()
        smooth(model, step)["smooth"].backward()
        opt.step()
    assert abs(float(model.height.detach())) < 0.05
    assert float(smooth(model, 0)["smooth"].detach()) < 0.3 * first


@pytest.mark.parametrize("support", ["table", "wall"])
def test_the_plan_smooths_depth_where_the_field_starts_empty_though_it_has_silhouettes_and_says_why(
        support: str) -> None:
    """train.smoothness=auto: on for a masked ball hung on a wall (its fast field starts empty), off on a table (it
    starts in the hull) and without silhouettes; on / off force it; the step then carries the term."""
    images, c2w, intr = masked_ball_photos(size=32, fl=40.0)
    frames, views = [], []
    for i, (image, pose, k) in enumerate(zip(images, c2w.double().numpy(), intr.tolist(), strict=True)):
        frames.append(Frame(f"/p/{i:02d}.png", pose, *k, 32, 32, split="train"))
        views.append(View(f"{i:02d}", image, pose, tuple(k), 1.0, 4.0))
    ground = {"table": np.array([0.0, 0.0, 1.0, -0.5]), "wall": np.array([0.0, -1.0, 0.0, -0.5])}[support]
    scene = Scene(frames=frames, aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="object", has_alpha=True,
                  ground=ground)
    cpu = torch.device("cpu")

    def plan(cfg: TrainConfig, photos: list = views) -> tuple[bool, str, int]:
        p = plan_training(cfg, replace(scene, has_alpha=photos is views), photos, cpu)
        said = " ".join(r for r in p.reasons if r.startswith("depth smoothness:"))
        terms = [piece for piece in build_training(p, cpu).step_kwargs["pieces"]
                 if isinstance(getattr(piece, "prior", None), PatchSmoothness)]
        return p.smoothness is not None, said, len(terms)

    base = replace(TrainConfig(), smoothness_patches=4)
    on, said, terms = plan(base)
    assert on == (support == "wall") and terms == int(on)
    assert ("starts empty though the photos have silhouettes" in said) == on
    assert ("starts in the photos' visual hull" in said) == (not on)
    on, said, terms = plan(replace(base, smoothness="on"))
    assert on and terms == 1 and "train.smoothness=on" in said and "8 px apart" in said
    assert "5 px apart" in plan(replace(base, smoothness="on", smoothness_stride=5))[1]
    assert plan(replace(base, smoothness="off"))[0] is False
    opaque = [replace(v, image=np.ascontiguousarray(v.image[..., :3])) for v in views]
    on, said, _ = plan(base, opaque)
    assert not on and "no silhouettes" in said
