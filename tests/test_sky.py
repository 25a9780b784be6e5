"""The sky of an unbounded capture (issue 11, sceaux_castle's blobs above the roofs): which pixels are sky, when the
train stage models one, the fast field's sky colour, and the empty-space loss on the sky's rays."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from recon.camera import look_at
from recon.capture.scene import Frame, Scene
from recon.capture.sky import SKY_POINT_MARGIN, sky_mask
from recon.config import TrainConfig
from recon.evaluation.views import View
from recon.nerf.fast import FastConfig, FastModel, SkyColor
from recon.nerf.fitting import RayBatcher
from recon.nerf.pieces import EmptyRays
from recon.nerf.trainer import train
from recon.plans.training import sky_for

RNG = np.random.default_rng(0)
H, W, ROOF = 60, 80, 30


def _castle(sky: tuple[float, float, float] = (0.35, 0.55, 0.9), wall: np.ndarray | None = None) -> np.ndarray:
    """Rows above ROOF a clear sky that brightens towards the horizon, below a textured building."""
    img = np.zeros((H, W, 3))
    t = np.linspace(0.0, 1.0, ROOF)[:, None, None]
    img[:ROOF] = np.asarray(sky) + t * 0.12  # ~0.004 per row: smooth
    img[ROOF:] = RNG.uniform(0.2, 0.8, (H - ROOF, W, 3)) if wall is None else wall
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


def _roof_points() -> np.ndarray:
    """SfM points along the building's top edge and on its face: none in the sky."""
    x = np.arange(2.0, W, 4.0)
    return np.concatenate([np.stack([x, np.full_like(x, ROOF + 0.5)], 1),
                           np.stack([x, np.full_like(x, ROOF + 15.5)], 1)])


def test_a_clear_sky_above_a_textured_building_is_sky_up_to_a_margin_from_the_roof_points() -> None:
    mask = sky_mask(_castle(), _roof_points())
    margin = round(SKY_POINT_MARGIN * W)
    assert not mask[ROOF:].any()  # the building is never sky
    assert mask[: ROOF - margin - 1].all()  # every sky row clear of the roof's points is sky
    assert mask.sum() < ROOF * W  # ... and the points keep a band above the roof out


def test_no_sky_where_points_are_seen_where_it_is_grey_or_where_it_does_not_reach_the_top() -> None:
    points = _roof_points()
    in_sky = np.concatenate([points, [[W / 2, 8.0]]])  # a point seen in the "sky": something is there
    mask = sky_mask(_castle(), in_sky)
    assert not mask[8, W // 2] and mask[8, 5]
    overcast = sky_mask(_castle(sky=(0.8, 0.8, 0.8)), points)  # a white sky cannot be told from a white wall
    assert not overcast.any()
    # a smooth blue wall below a textured band: blue and smooth, but not reached from the top edge
    img = _castle(wall=np.array([0.3, 0.5, 0.9]))
    img[:ROOF] = np.round(RNG.uniform(0.2, 0.8, (ROOF, W, 3)) * 255)
    assert not sky_mask(img, np.zeros((0, 2))).any()


def test_pale_haze_beside_the_blue_sky_is_sky_and_a_pale_sky_alone_is_not() -> None:
    img = _castle()
    t = np.clip(1.0 - np.arange(W) / (W / 2), 0.0, 1.0)[None, :, None]  # towards the sun on the left, pale haze
    img[:ROOF] = np.round(img[:ROOF] * (1 - t) + t * np.array([0.9, 0.9, 0.92]) * 255)
    mask = sky_mask(img, _roof_points())
    pale = img[:10, :, 2].astype(float) <= img[:10, :, 0] + 0.05 * 255
    assert pale.sum() >= 20  # not blue, so sky only as grown from the blue
    assert mask[:10].all()
    assert not mask[ROOF:].any()
    img[:ROOF] = img[0, 0]  # all haze: no blue to grow from
    assert not sky_mask(img, _roof_points()).any()


def _views(images: list[np.ndarray]) -> tuple[list[Frame], list[View]]:
    frames = [Frame(file_path=f"images/p{i}.png", c2w=np.eye(4), w=W, h=H, fl_x=60.0, fl_y=60.0, cx=W / 2, cy=H / 2)
              for i in range(len(images))]
    views = [View(f.name, im, np.eye(4), (60.0, 60.0, W / 2, H / 2), 0.1, 10.0) for f, im in zip(frames, images)]
    return frames, views


def _scene(frames: list[Frame], capture: str = "unbounded", has_alpha: bool = False, points: bool = True) -> Scene:
    # points on the building's face: 2 units in front of the (identity) cameras, 15 rows below the roof
    uv = _roof_points()
    xyz = np.stack([(uv[:, 0] - W / 2) / 60.0 * 2.0, -(uv[:, 1] - H / 2) / 60.0 * 2.0, np.full(len(uv), -2.0)], 1)
    return Scene(frames=frames, aabb=((-1, -1, -1), (1, 1, 1)), capture=capture, has_alpha=has_alpha,
                 points=xyz if points else np.zeros((0, 3)),
                 point_visibility={f.name: np.arange(len(uv)) for f in frames} if points else {})


@pytest.mark.parametrize("mode, kind, capture, alpha, points, images, on, says", [
    ("auto", "fast", "unbounded", False, True, "castle", True, "sky: on ("),
    ("auto", "fast", "unbounded", False, True, "room", False, "fewer than 1%"),
    ("auto", "fast", "object", False, True, "castle", False, "an object capture"),
    ("on", "fast", "object", False, True, "castle", True, "train.sky=on"),
    ("auto", "fast", "unbounded", True, True, "castle", False, "masks"),
    ("auto", "classic", "unbounded", False, True, "castle", False, "classic model"),
    ("auto", "fast", "unbounded", False, False, "castle", False, "no sparse points"),
    ("off", "fast", "unbounded", False, True, "castle", False, "train.sky=off"),
])
def test_the_sky_is_modelled_by_model_capture_and_photos_and_says_why(mode: str, kind: str, capture: str, alpha: bool,
                                                                    points: bool, images: str, on: bool, says: str) -> None:
    photos = [_castle() if images == "castle" else _castle(wall=None, sky=(0.8, 0.75, 0.7)) for _ in range(3)]
    frames, views = _views(photos)
    masks, why = sky_for(TrainConfig(sky=mode), kind, _scene(frames, capture, alpha, points), frames, views)
    assert says in why
    assert (masks is not None) == on
    if on:  # the points project onto the building's face, so the sky is found with its margin above the roof
        assert all(not m[ROOF:].any() and m[: ROOF - 4].all() for m in masks)


def test_the_batcher_carries_the_empty_masks_with_each_ray() -> None:
    images = [torch.from_numpy(_castle()) for _ in range(2)]
    masks = [torch.from_numpy(sky_mask(im.numpy(), _roof_points())) for im in images]
    c2w = torch.eye(4).expand(2, 4, 4).clone()
    intr = torch.tensor([[60.0, 60.0, W / 2, H / 2]] * 2)
    batcher = RayBatcher(images, c2w, intr, near_far=torch.tensor([0.1, 10.0]), empty=masks, seed=0)
    flat_masks = torch.cat([m.reshape(-1) for m in masks]).float()
    flat_rgb = torch.cat([im.reshape(-1, 3) for im in images]).float() / 255
    seen = 0
    for _ in range(3):
        batch = batcher.next_batch(500)
        sky = batch["empty"] > 0
        assert 0 < int(sky.sum()) < 500
        seen += int(sky.sum())
        # each ray's mask value belongs to its pixel: sky rays show the sky's blue, the others the building
        assert bool((batch["rgb"][sky, 2] > batch["rgb"][sky, 0] + 0.2).all())
    assert abs(seen / 1500 - float(flat_masks.mean())) < 0.08
    assert flat_rgb.shape[0] == flat_masks.shape[0]
    with pytest.raises(ValueError, match="one \\(H, W\\) mask per image"):
        RayBatcher(images, c2w, intr, near_far=torch.tensor([0.1, 10.0]), empty=masks[:1])


def test_the_batcher_carries_weighted_empty_masks_to_a_255th() -> None:
    """Float masks are weights of each pixel's empty-space loss (the disputed transparent pixels pay a share)."""
    images = [torch.from_numpy(_castle()) for _ in range(2)]
    weights = [torch.full(im.shape[:2], w) for im, w in zip(images, (0.3, 0.8), strict=True)]
    weights[1][:, : W // 2] = 0.0  # half of the second photo is not known empty at all
    c2w = torch.eye(4).expand(2, 4, 4).clone()
    intr = torch.tensor([[60.0, 60.0, W / 2, H / 2]] * 2)
    batch = RayBatcher(images, c2w, intr, near_far=torch.tensor([0.1, 10.0]), empty=weights, seed=0).next_batch(600)
    first, second = batch["empty"][batch["image"] == 0], batch["empty"][batch["image"] == 1]
    assert first.numel() > 100 and second.numel() > 100
    assert torch.allclose(first, torch.full_like(first, round(0.3 * 255) / 255))
    assert torch.allclose(second.unique(), torch.tensor([0.0, round(0.8 * 255) / 255]))


def test_the_sky_colour_starts_grey_and_is_what_an_empty_field_shows() -> None:
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    torch.testing.assert_close(SkyColor()(d), torch.full((50, 3), 0.5))
    model = FastModel(FastConfig(background="sky", density_res=16, feature_res=8, feature_dim=4, occupancy_res=8,
                                 mlp_width=16, mlp_layers=1, init_alpha=1e-6))
    with torch.no_grad():
        model.sky.linear.bias.copy_(torch.tensor([-1.0, 0.0, 2.0]))
        model.sky.linear.weight[2, 2] = 1.0  # the SH term in z (up in the scene): bluer upwards
        out = model.render_rays(torch.zeros(50, 3), d, torch.full((50,), 0.1), torch.full((50,), 1.0), training=False)
        assert float(out["opacity"].max()) < 1e-3
        torch.testing.assert_close(out["rgb"], model.sky(d), atol=2e-3, rtol=0)
    assert float(torch.corrcoef(torch.stack([out["rgb"][:, 2], d[:, 2]]))[0, 1]) > 0.9


def _sky_photos(n: int = 6, size: int = 16, fl: float = 12.0):
    """Cameras on a ring looking outwards and up at a sky that is bluer towards the zenith: nothing but sky."""
    c2w = np.stack([look_at(np.zeros(3), np.array([math.cos(a), math.sin(a), 0.8])) for a in
                    np.linspace(0, 2 * math.pi, n, endpoint=False)])
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    images = []
    for pose in c2w:
        d = np.stack([(xs - size / 2) / fl, -(ys - size / 2) / fl, -np.ones_like(xs)], -1) @ pose[:3, :3].T
        up = (d / np.linalg.norm(d, axis=-1, keepdims=True))[..., 2]
        rgb = np.stack([0.6 - 0.4 * up, 0.7 - 0.3 * up, np.full_like(up, 0.95)], -1)
        images.append(torch.from_numpy(np.round(rgb * 255).astype(np.uint8)))
    intr = torch.tensor([[fl, fl, size / 2, size / 2]] * n)
    return images, torch.tensor(c2w, dtype=torch.float32), intr


@pytest.mark.parametrize("sky", [False, True])
def test_without_a_sky_the_field_paints_the_sky_into_its_density_and_with_it_stays_empty(sky: bool) -> None:
    """The castle's blobs in miniature: rays that see only a graded sky. With one background colour the field must
    put density on them to show the grade; with the sky colour and the empty-space term, it stays empty."""
    torch.manual_seed(0)
    images, c2w, intr = _sky_photos()
    cfg = FastConfig(unbounded=True, background="sky" if sky else "white", density_res=24, feature_res=16, feature_dim=4,
                     occupancy_res=8, occupancy_warmup=4, occupancy_every=2, mlp_width=16, mlp_layers=1)
    model = FastModel(cfg)
    empty = [torch.ones(im.shape[:2], dtype=torch.bool) for im in images] if sky else None
    batcher = RayBatcher(images, c2w, intr, near_far=torch.tensor([0.05, 1e3]), empty=empty, seed=0)
    result = train(model, batcher, steps=150, lr=2e-2, batch_rays=256, pieces=[EmptyRays(0.1)] if sky else [])
    model.eval()
    batch = batcher.next_batch(512)
    with torch.no_grad():
        out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"], training=False,
                                background=torch.ones(3))
    opacity = float(out["opacity"].mean())
    error = float((out["rgb"] - batch["rgb"]).abs().mean())
    if sky:
        assert opacity < 0.05, opacity
        assert error < 0.03, (error, result["psnr"])
    else:
        assert opacity > 0.3, opacity  # the blobs: only density can draw the blue on a white background
