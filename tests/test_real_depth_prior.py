"""Sparse-depth supervision from SfM points (issue 11, "few photos"): targets, uncertainty, the loss's closed
form and gradient, and that a field trained with it puts its surface at the points' depth."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from recon.camera import look_at
from recon.camera import triangulation_angles
from recon.nerf.depth_prior import DepthPrior, depth_loss, sparse_depth_targets
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.fitting import RayBatcher
from recon.nerf.pieces import DepthPriorLoss
from recon.nerf.trainer import train

W, H, FL = 64, 48, 60.0


def test_depth_loss_is_zero_at_the_target_and_pulls_toward_it() -> None:
    target = torch.tensor([2.0, 3.0, 4.0])
    sigma = torch.tensor([0.1, 0.5, 0.02])
    assert float(depth_loss(target.clone(), target, sigma)) == 0.0
    for shift, sign in ((0.3, 1.0), (-0.3, -1.0)):
        depth = (target + shift).requires_grad_(True)
        loss = depth_loss(depth, target, sigma)
        loss.backward()
        assert float(loss.detach()) > 0
        assert bool((torch.sign(depth.grad) == sign).all())  # descent moves the depth back to the target
        # robust: the gradient of one ray never exceeds 1 / (sigma · N)
        assert bool((depth.grad.abs() <= 1.0 / (sigma * 3) + 1e-6).all())
    # within one sigma it is a Gaussian's negative log-likelihood, r² / 2
    r = 1e-2
    assert float(depth_loss(torch.tensor([1.0 + r]), torch.tensor([1.0]), torch.tensor([1.0]))) == pytest.approx(r * r / 2, rel=1e-3)


def test_triangulation_angle_of_two_perpendicular_rays() -> None:
    centers = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
    points = np.zeros((2, 3))
    visible = [np.array([0, 1]), np.array([0]), np.array([], np.int64)]
    angles = triangulation_angles(points, centers, visible)
    assert angles[0] == pytest.approx(math.pi / 2)
    assert angles[1] == 0.0  # seen once: no triangulation


def _cams() -> np.ndarray:
    return np.stack([look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.5]), np.zeros(3)) for a in (0.0, 0.6)])


def test_targets_pass_through_the_points_with_triangulation_uncertainty() -> None:
    c2w = _cams()
    k = np.array([[FL, FL, W / 2, H / 2]] * 2)
    sizes = np.array([[W, H]] * 2)
    points = np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.1], [6.0, 0.0, 0.0], [0.0, 0.0, 3.0]])  # 2: behind cam 0; 3: out of frame
    visible = [np.array([0, 1, 2, 3]), np.array([0, 1])]
    t = sparse_depth_targets(points, visible, c2w, k, sizes, 1.0)
    assert t.view.tolist() == [0, 0, 1, 1]
    hit = t.rays_o + t.depth[:, None] * t.rays_d
    np.testing.assert_allclose(hit.numpy(), points[[0, 1, 0, 1]], atol=1e-5)
    np.testing.assert_allclose(torch.linalg.vector_norm(t.rays_d, dim=-1).numpy(), 1.0, atol=1e-6)
    theta = triangulation_angles(points, c2w[:, :3, 3], visible)[[0, 1, 0, 1]]
    expected = t.depth.numpy() * 1.0 / (FL * np.sin(theta))
    np.testing.assert_allclose(t.sigma.numpy(), expected, rtol=1e-5)
    # twice the reprojection error, twice the uncertainty; a floor keeps it above min_sigma
    t2 = sparse_depth_targets(points, visible, c2w, k, sizes, 2.0)
    np.testing.assert_allclose(t2.sigma.numpy(), 2 * t.sigma.numpy(), rtol=1e-5)
    t3 = sparse_depth_targets(points, visible, c2w, k, sizes, 1.0, min_sigma=10.0)
    assert bool((t3.sigma == 10.0).all())
    # a mask that calls the image background everywhere leaves no target in that photo
    t4 = sparse_depth_targets(points, visible, c2w, k, sizes, 1.0, alpha=[np.zeros((H, W), np.uint8), None])
    assert t4.view.tolist() == [1, 1]


def test_field_trained_with_the_depth_prior_puts_its_surface_at_the_points() -> None:
    """A flat grey wall at x = 0 seen from two cameras: colours alone say nothing about where the wall is; the
    sparse points on it do. With the prior, rendered depth at the points matches them."""
    torch.manual_seed(0)
    angles = np.radians([-12.0, 12.0])
    c2w = np.stack([look_at(np.array([2.5 * math.cos(a), 2.5 * math.sin(a), 0.0]), np.array([0.0, 0.0, 0.0])) for a in angles])
    k = np.array([[FL, FL, W / 2, H / 2]] * 2)
    rng = np.random.default_rng(0)
    points = np.column_stack([np.zeros(60), rng.uniform(-0.5, 0.5, 60), rng.uniform(-0.3, 0.3, 60)])
    visible = [np.arange(60), np.arange(60)]
    targets = sparse_depth_targets(points, visible, c2w, k, np.array([[W, H]] * 2), 0.5)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    images = torch.full((2, H, W, 3), 0.5)
    tiny = dict(density_res=32, feature_res=16, feature_dim=4, occupancy_res=8, occupancy_warmup=4,
                occupancy_every=4, mlp_width=16, mlp_layers=1)

    def fit(weight: float) -> float:
        torch.manual_seed(0)
        model = FastModel(FastConfig(aabb=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), **tiny))
        batcher = RayBatcher(images, torch.tensor(c2w, dtype=torch.float32), torch.tensor(k, dtype=torch.float32),
                             aabb=aabb, background=(0.0, 0.0, 0.0))
        prior = DepthPrior(targets, weight, 64, aabb=aabb)
        assert len(prior) == len(targets) == 120
        train(model, batcher, steps=60, lr=3e-2, batch_rays=256, pieces=[DepthPriorLoss(prior)])
        with torch.no_grad():
            near, far, _ = __import__("recon.nerf.rays", fromlist=["ray_aabb"]).ray_aabb(prior.rays_o, prior.rays_d, aabb)
            out = model.render_rays(prior.rays_o, prior.rays_d, near, far, training=False)
        return float((out["depth"] - prior.depth).abs().median())

    with_prior, without = fit(0.01), fit(0.0)
    assert with_prior < 0.05  # the surface sits within a few voxels (0.0625) of the points
    assert with_prior < 0.5 * without


def _scene_with_points(n_views: int) -> tuple:
    """A Scene of n_views cameras around the origin with 40 sparse points near it that every camera observes,
    and its views (tiny grey images)."""
    from recon.capture.scene import Frame, Scene
    from recon.config import TrainConfig
    from recon.evaluation.views import View

    frames, views = [], []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        c2w = look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 1.0]), np.zeros(3))
        frames.append(Frame(f"/p/{i:02d}.jpg", c2w, FL * 2, FL * 2, W, H, 2 * W, 2 * H, split="train"))
        views.append(View(f"{i:02d}", np.full((H, W, 3), 128, np.uint8), c2w, (FL, FL, W / 2, H / 2), 1.0, 5.0))
    points = np.random.default_rng(0).uniform(-0.3, 0.3, (40, 3))
    scene = Scene(frames=frames, points=points, point_visibility={f.name: np.arange(40) for f in frames},
                  point_errors=np.full(40, 0.8), aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="object")
    return TrainConfig(), scene, frames, views


@pytest.mark.parametrize("n_views, mode, masks, kind, capture, on", [
    (15, "auto", False, "fast", "object", True), (24, "auto", False, "fast", "object", False),
    (24, "on", False, "fast", "object", True), (15, "off", False, "fast", "object", False),
    (15, "auto", True, "fast", "object", True), (15, "on", True, "fast", "object", True),
    (15, "auto", True, "surface", "object", False),
    (24, "auto", False, "surface", "object", True), (24, "auto", True, "surface", "object", False),
    (24, "off", False, "surface", "object", False),
    (24, "auto", False, "fast", "unbounded", True), (24, "auto", True, "fast", "unbounded", False),
    (24, "off", False, "fast", "unbounded", False),
])
def test_depth_prior_is_switched_on_by_few_views_and_says_why(n_views: int, mode: str, masks: bool, kind: str,
                                                             capture: str, on: bool) -> None:
    from dataclasses import replace

    from recon.plans.training import depth_prior_for

    cfg, scene, frames, views = _scene_with_points(n_views)
    cfg, scene = replace(cfg, depth_prior=mode), replace(scene, capture=capture)
    if masks:  # photos with masks: alpha 255 everywhere (all object), so every point stays a target when forced on
        scene.has_alpha = True
        views = [replace(v, image=np.concatenate([v.image, np.full(v.image.shape[:2] + (1,), 255, np.uint8)], -1)) for v in views]
    model_cfg = {"sdf_res": 64} if kind == "surface" else {"density_res": 64}
    prior, why = depth_prior_for(cfg, kind, scene, frames, views, {"config": model_cfg})
    assert (prior is not None) == on and why.startswith(f"depth prior: {'on' if on else 'off'}")
    if mode == "auto" and kind == "surface" and on:
        assert "surface model" in why and "concavity" in why  # the model decided it, whatever the photo count
    elif mode == "auto" and capture == "unbounded" and on:
        assert "unbounded capture" in why  # the background decided it, whatever the photo count
    elif mode == "auto":
        assert f"{n_views} training photos" in why
    if masks and mode == "auto":  # the number of views decided it, and the reason says what the masks do
        assert ("few silhouettes carve no concavity" if on else "but masks") in why
    if on:
        assert len(prior) == 40 * n_views and "DS-NeRF" in why
        # errors are in original-photo pixels (2x the training images): 0.8 px there is 0.4 px here, floored at 0.5
        assert bool((prior.sigma >= 2.0 / 64 - 1e-6).all())  # never finer than the field's voxel


@pytest.mark.parametrize("mode, cull_slowly, on", [("auto", True, True), ("auto", False, False),
                                                  ("off", True, False)])
def test_depth_prior_is_on_for_a_masked_field_that_starts_empty(mode: str, cull_slowly: bool, on: bool) -> None:
    """24 masked photos of an object would leave the prior off; a fast field that starts empty though they have
    silhouettes (an object on a wall) takes it, and says why."""
    from dataclasses import replace

    from recon.plans.training import depth_prior_for

    cfg, scene, frames, views = _scene_with_points(24)
    cfg = replace(cfg, depth_prior=mode)
    scene.has_alpha = True
    views = [replace(v, image=np.concatenate([v.image, np.full(v.image.shape[:2] + (1,), 255, np.uint8)], -1))
             for v in views]
    prior, why = depth_prior_for(cfg, "fast", scene, frames, views, {"config": {"density_res": 64}}, cull_slowly)
    assert (prior is not None) == on and why.startswith(f"depth prior: {'on' if on else 'off'}")
    if on:
        assert "starts empty" in why and "wall" in why
    elif mode == "auto":
        assert "the photos constrain the geometry" in why


@pytest.mark.parametrize("mode, hollow, on", [("auto", 0.3, True), ("auto", 0.02, False), ("auto", None, False),
                                              ("off", 0.3, False)])
def test_depth_prior_is_on_for_a_masked_field_whose_hull_has_a_hollow(mode: str, hollow: float | None,
                                                                       on: bool) -> None:
    """24 masked photos of an object leave the prior off, unless their sightlines to the sparse points pass through
    HOLLOW_SHARE of their silhouettes' hull or more (a bowl, which the silhouettes fill): it says why either way."""
    from dataclasses import replace

    from recon.plans.training import depth_prior_for

    cfg, scene, frames, views = _scene_with_points(24)
    cfg = replace(cfg, depth_prior=mode)
    scene.has_alpha = True
    views = [replace(v, image=np.concatenate([v.image, np.full(v.image.shape[:2] + (1,), 255, np.uint8)], -1))
             for v in views]
    prior, why = depth_prior_for(cfg, "fast", scene, frames, views, {"config": {"density_res": 64}}, hollow=hollow)
    assert (prior is not None) == on and why.startswith(f"depth prior: {'on' if on else 'off'}")
    if on:
        assert "30% of their silhouettes' visual hull" in why and "hollow" in why
    elif mode == "auto":
        assert ("no hollow" in why and "2% of" in why) == (hollow is not None)


def test_a_bowls_hull_is_mostly_hollow_and_a_balls_is_not() -> None:
    """`hollow_share`: the sightlines from cameras above to points inside a bowl pass through most of its silhouettes'
    hull (the half-ball); to points on a ball's upper half, through little of its hull."""
    from recon.capture.scene import Scene
    from recon.evaluation.views import View
    from recon.plans.training import hollow_share

    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    views, lines = [], []
    for i in range(16):
        a = 2 * math.pi * i / 16
        c2w = look_at(np.array([2.5 * math.cos(a), 2.5 * math.sin(a), 2.0]), np.zeros(3))
        v, u = np.mgrid[0:H, 0:W] + 0.5
        ray = np.stack([(u - W / 2) / FL, -(v - H / 2) / FL, -np.ones_like(u)], -1) @ c2w[:3, :3].T
        ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
        o = c2w[:3, 3]
        b = ray @ o
        hit = (b**2 - (o @ o - 0.5**2) > 0) & (-b > 0)  # the ball of radius 0.5; the bowl is its lower half
        root = np.sqrt(np.maximum(b**2 - (o @ o - 0.25), 0))
        low = np.minimum(o[2] + (-b - root) * ray[..., 2], o[2] + (-b + root) * ray[..., 2]) < 0  # meets the lower half
        views.append((c2w, hit, hit & low))
    scene = Scene(frames=[], points=np.zeros((0, 3)), aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="object")
    inner = 0.35 * d * np.where(d[:, 2:] < 0, 1.0, -1.0)
    outer = 0.5 * d * np.where(d[:, 2:] > 0, 1.0, -1.0)
    for points, k in ((inner, 2), (outer, 1)):
        grey = np.full((H, W, 3), 128, np.uint8)
        shown = [View(f"{i}", np.concatenate([grey, (sil[k] * 255).astype(np.uint8)[..., None]], -1), sil[0],
                      (FL, FL, W / 2, H / 2), 1.0, 5.0) for i, sil in enumerate(views)]
        seen = []
        for c2w, *_ in views:
            eye = c2w[:3, 3]
            if k == 2:  # inside the bowl: seen through its opening
                t = eye[2] / (eye[2] - points[:, 2])
                seen.append(np.linalg.norm(eye[:2] + t[:, None] * (points[:, :2] - eye[:2]), axis=1) < 0.35)
            else:  # on the ball: seen from the side it faces
                seen.append(np.einsum("ij,ij->i", points, eye - points) > 0)
        lines.append([(sil[0][:3, 3], points[ok]) for sil, ok in zip(views, seen)])
        share = hollow_share(scene, shown, lines[-1])
        assert (share > 0.3) if k == 2 else (share < 0.1), share


def test_point_errors_survive_save_load_and_normalize(tmp_path) -> None:
    from recon.capture.normalization import normalize
    from recon.capture.scene import load_scene
    from recon.config import NormalizeConfig

    _, scene, _, _ = _scene_with_points(12)
    scene.points[3] = np.nan  # dropped by normalize: the errors must stay aligned with the points
    scene.point_errors = np.arange(40, dtype=np.float64)
    out = normalize(scene, NormalizeConfig())
    assert out.point_errors is not None and len(out.point_errors) == len(out.points) == 39
    assert out.point_errors[3] == 4.0
    out.save(tmp_path)
    np.testing.assert_array_equal(load_scene(tmp_path).point_errors, out.point_errors)
