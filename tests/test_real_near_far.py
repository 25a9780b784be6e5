"""near/far are distances along unit-length rays (recon.capture.scene.RAY_DISTANCE), not depths along the optical axis.

A corner ray travels depth / cos(angle) to reach the depth the centre ray reaches at `depth`; with axial
depths used as ray distances, off-axis rays stopped short of the far surface (issue 11, defect 2).
"""
from __future__ import annotations

import numpy as np
import torch

from recon.camera import look_at
from recon.capture.normalization import _box_distance_range, _distance_range, normalize
from recon.capture.scene import Frame, Scene
from recon.config import NormalizeConfig
from recon.nerf.rays import camera_rays, ray_aabb

W, H, FL = 320, 240, 160.0  # a wide lens: the corner ray is 51° off-axis


def rays(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o, d = camera_rays(torch.as_tensor(c2w, dtype=torch.float64), FL, FL, W / 2, H / 2, W, H)
    return o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()


def test_corner_and_centre_rays_reach_the_far_face_of_the_box() -> None:
    c2w = np.eye(4)  # at the origin, looking down -Z
    aabb = np.array([[-50.0, -50.0, -5.0], [50.0, 50.0, -4.0]])  # a slab: every ray leaves through z = -5
    near, far = _box_distance_range(c2w, aabb)
    o, d = rays(c2w)
    centre, corner = (H // 2) * W + W // 2, 0
    for i in (centre, corner):
        assert (o[i] + far * d[i])[2] <= -5.0 + 1e-9  # at t = far the ray is at or beyond the far face
        assert (o[i] + near * d[i])[2] >= -4.0 - 1e-9  # at t = near it has not yet entered the box
    t_near, t_far, hit = ray_aabb(torch.as_tensor(o), torch.as_tensor(d), torch.as_tensor(aabb))
    assert bool(hit.all()) and float(t_far.max()) <= far + 1e-9 and float(t_near.min()) >= near - 1e-9
    assert abs(near - 4.0) < 1e-12  # the box's nearest point is straight ahead


def test_rays_reach_the_far_wall_the_points_lie_on() -> None:
    c2w = look_at(np.array([1.0, 2.0, 0.5]), np.array([1.0, 2.0 + 10.0, 0.5]))  # wall 10 units ahead
    o, d = rays(c2w)
    forward = -c2w[:3, 2]
    t_wall = 10.0 / (d @ forward)  # where each pixel's ray meets the wall
    points = o + t_wall[:, None] * d
    near, far = _distance_range(c2w, points[::7], percentile=0.0)
    centre, corner = (H // 2) * W + W // 2, 0
    # the corner ray must travel the farthest to reach the wall; at t = far both reach it
    for i in (centre, corner):
        assert (o[i] + far * d[i] - o[i]) @ forward >= 10.0 - 1e-6
    assert far >= t_wall[corner] - 1e-6 and abs(far - t_wall.max()) < 0.05
    assert abs(near - 10.0) < 0.05


def test_normalized_object_scene_every_pixel_ray_ends_past_the_box() -> None:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(12):
        az = 2 * np.pi * i / 12
        eye = 2.2 * np.array([np.cos(az), np.sin(az), 0.4])
        frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), FL, FL, W / 2, H / 2, W, H))
    points = rng.uniform(-0.8, 0.8, size=(500, 3))
    scene = normalize(Scene(frames=frames, points=points, point_colors=np.zeros((500, 3), np.uint8)), NormalizeConfig())
    box = torch.as_tensor(scene.aabb)
    for f in scene.frames:
        o, d = rays(f.c2w)
        t_near, t_far, hit = ray_aabb(torch.as_tensor(o), torch.as_tensor(d), box)
        assert float(t_far[hit].max()) <= f.far + 1e-9, f.name
        assert float(t_near[hit].min()) >= f.near - 1e-9, f.name
