"""Pinhole rays (OpenGL convention, pixel centres) and ray/box intersection."""
from __future__ import annotations

import math

import pytest
import torch

from recon.camera import look_at
from recon.nerf.rays import camera_rays, pixel_rays, ray_aabb


def _look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """OpenGL c2w (`recon.camera.look_at`) as a tensor of eye's dtype."""
    return torch.as_tensor(look_at(eye.numpy(), target.numpy()), dtype=eye.dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identity_camera_matches_pinhole_closed_form(dtype: torch.dtype) -> None:
    w, h, f, cx, cy = 6, 4, 5.0, 3.0, 2.0
    o, d = camera_rays(torch.eye(4, dtype=dtype), f, f, cx, cy, w, h)
    assert o.shape == d.shape == (h, w, 3) and d.dtype == dtype
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(h, w, dtype=dtype))
    # pixel (column 0, row 0) centre (0.5, 0.5): left (-x) and up (+y) of the axis, looking down -z
    expected = torch.tensor([(0.5 - cx) / f, -(0.5 - cy) / f, -1.0], dtype=dtype)
    torch.testing.assert_close(d[0, 0], expected / expected.norm())
    assert d[0, 0, 0] < 0 and d[0, 0, 1] > 0 and d[0, 0, 2] < 0
    # centred principal point: symmetric rays
    torch.testing.assert_close(d[:, :, 0], -d.flip(1)[:, :, 0])
    torch.testing.assert_close(d[:, :, 1], -d.flip(0)[:, :, 1])


def test_rays_project_back_to_their_pixels() -> None:
    c2w = _look_at(torch.tensor([3.0, -2.0, 1.5]), torch.zeros(3))
    w, h, fx, fy, cx, cy = 8, 5, 7.0, 6.5, 4.2, 2.4
    o, d = camera_rays(c2w, fx, fy, cx, cy, w, h)
    pts = o + 2.7 * d  # world points along the rays
    w2c = torch.linalg.inv(c2w)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    u = fx * cam[..., 0] / -cam[..., 2] + cx
    v = -fy * cam[..., 1] / -cam[..., 2] + cy
    jj, ii = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    torch.testing.assert_close(u, ii, atol=1e-4, rtol=0)
    torch.testing.assert_close(v, jj, atol=1e-4, rtol=0)
    # camera looks at the origin: the principal ray points to it
    o1, d1 = pixel_rays(c2w[None], *(torch.tensor([x]) for x in (fx, fy, cx, cy, cx, cy)))
    torch.testing.assert_close(d1[0], -c2w[:3, 3] / c2w[:3, 3].norm())


def test_pixel_rays_equal_camera_rays() -> None:
    c2ws = torch.stack([_look_at(torch.tensor([0.0, 4.0, 1.0]), torch.zeros(3)), _look_at(torch.tensor([-3.0, 1.0, 2.0]), torch.zeros(3))])
    w, h = 5, 3
    intr = torch.tensor([[4.0, 4.5, 2.5, 1.5], [3.0, 3.0, 2.0, 1.0]])
    idx_img = torch.tensor([0, 1, 1, 0])
    px, py = torch.tensor([0, 4, 2, 3]), torch.tensor([0, 2, 1, 1])
    o, d = pixel_rays(c2ws[idx_img][:, :3], *intr[idx_img].T, px + 0.5, py + 0.5)
    for k in range(4):
        oc, dc = camera_rays(c2ws[idx_img[k]], *intr[idx_img[k]].tolist(), w, h)
        torch.testing.assert_close(o[k], oc[py[k], px[k]])
        torch.testing.assert_close(d[k], dc[py[k], px[k]])


def test_ray_aabb_closed_forms_and_axis_parallel_rays() -> None:
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    o = torch.tensor([
        [-3.0, 0.0, 0.0],   # along +x through the centre: [2, 4]
        [-3.0, 2.0, 0.0],   # parallel to x, outside in y: miss
        [0.0, 0.0, 0.0],    # inside, diagonal: starts at 0
        [0.0, 0.0, 3.0],    # pointing away: miss
        [-3.0, 1.0, 0.0],   # grazing the face y=1 (parallel, on the boundary): degenerate, treated as hit
        [-3.0, -3.0, 0.5],  # diagonal in xy
    ])
    d = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1, 1, 1], [0, 0, 1.0], [1.0, 0, 0], [1.0, 1.0, 0]])
    d = d / d.norm(dim=-1, keepdim=True)
    near, far, hit = ray_aabb(o, d, aabb)
    assert hit.tolist() == [True, False, True, False, True, True]
    torch.testing.assert_close(near, torch.tensor([2.0, 0, 0, 0, 2.0, 2 * math.sqrt(2)]))
    torch.testing.assert_close(far, torch.tensor([4.0, 0, math.sqrt(3), 0, 4.0, 4 * math.sqrt(2)]))
    assert torch.isfinite(near).all() and torch.isfinite(far).all()


def test_ray_aabb_random_points_inside_interval_are_inside_box() -> None:
    g = torch.Generator().manual_seed(0)
    o = torch.randn(2000, 3, generator=g, dtype=torch.float64) * 3
    d = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    d[:100, 0] = 0.0  # axis-parallel in x
    d[100:150, 1:] = 0.0  # parallel to x
    d = d / d.norm(dim=-1, keepdim=True)
    aabb = torch.tensor([[-1.0, -0.5, -2.0], [1.5, 0.5, 1.0]], dtype=torch.float64)
    near, far, hit = ray_aabb(o, d, aabb)
    s = torch.rand(2000, 1, generator=g, dtype=torch.float64)
    p = o + (near[:, None] + s * (far - near)[:, None]) * d
    inside = ((p >= aabb[0] - 1e-9) & (p <= aabb[1] + 1e-9)).all(-1)
    assert inside[hit].all()
    # a dense march along missed rays never enters the box
    ts = torch.linspace(0, 20, 2001, dtype=torch.float64)
    pm = o[~hit, None] + ts[None, :, None] * d[~hit, None]
    assert not ((pm > aabb[0]) & (pm < aabb[1])).all(-1).any()
    assert hit.sum() > 100


def test_bad_shapes_raise() -> None:
    with pytest.raises(ValueError, match="c2w must have shape"):
        camera_rays(torch.eye(3), 1.0, 1.0, 0.5, 0.5, 1, 1)
    with pytest.raises(ValueError, match=r"aabb must have shape \(2, 3\)"):
        ray_aabb(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(3))
