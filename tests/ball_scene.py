"""A tiny ground-truth scene for the training loop's tests: a red ball photographed from a ring of cameras, and a
classic model small enough to learn it in a few dozen steps.

Shared by tests/test_trainer.py and tests/test_numerics_train.py (test modules never import each other); the
masked ball photos by tests/test_train_pieces.py and tests/test_train_plan.py.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from recon.camera import look_at
from recon.nerf.classic import ClassicModel
from recon.nerf.evaluate import render_image
from recon.nerf.render import RadianceModel, render_dense
from recon.nerf.sampling import stratified

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
COLOR = torch.tensor([0.9, 0.2, 0.1])


class Ball(RadianceModel):
    """Ground truth: a red ball of radius 0.6 and density 30 at the origin; nothing to train."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("color", COLOR.clone())

    def density(self, x: Tensor) -> Tensor:
        return 30.0 * (x.norm(dim=-1) < 0.6).to(x.dtype)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return self.color.expand(x.shape[0], 3)

    def render_rays(self, rays_o, rays_d, near, far, *, training, background, colors=True):
        t = stratified(near, far, 128, jitter=False)
        x = rays_o[:, None] + t[..., None] * rays_d[:, None]
        sigma = self.density(x.reshape(-1, 3)).view(t.shape)
        rgb = self.color.expand(*t.shape, 3)
        return render_dense(sigma, rgb, t, far, background)


def ring_cameras(n_views: int) -> Tensor:
    """(n_views, 4, 4) float32 OpenGL camera-to-world on a ring of radius 3 at height 0.8, looking at the origin."""
    angles = torch.arange(n_views) * 2 * math.pi / n_views
    eyes = torch.stack([3 * torch.cos(angles), 3 * torch.sin(angles), torch.full_like(angles, 0.8)], dim=-1)
    return torch.stack([torch.tensor(look_at(eye.numpy(), np.zeros(3)), dtype=torch.float32) for eye in eyes])


def ball_views(n_views: int = 4, size: int = 12) -> tuple[Tensor, Tensor, Tensor]:
    """The ball rendered from `ring_cameras`: images (n, size, size, 3), c2w (n, 4, 4), intrinsics (n, 4)."""
    c2w = ring_cameras(n_views)
    f = size * 1.2
    intr = torch.tensor([[f, f, size / 2, size / 2]]).expand(n_views, 4).contiguous()
    images = torch.stack([render_image(Ball(), c, intr[0], size, size, aabb=AABB)["rgb"] for c in c2w])
    return images, c2w, intr


def tiny_model(seed: int = 0) -> ClassicModel:
    """A classic NeRF of a few thousand weights over AABB, seeded: learns the ball in tens of steps."""
    torch.manual_seed(seed)
    return ClassicModel(AABB, n_coarse=24, n_fine=0, pos_freqs=3, dir_freqs=1, depth=2, width=32, skip=0)


def masked_ball_photos(n: int = 12, size: int = 24, fl: float = 30.0,
                       radius: float = 0.45) -> tuple[list[np.ndarray], Tensor, Tensor]:
    """A ball photographed on a ring, RGBA (H, W, 4) uint8: opaque where a ray meets the ball, fully transparent
    elsewhere; camera-to-world (n, 4, 4) and intrinsics (n, 4) as tensors."""
    c2w = np.stack([look_at(np.array([2.5 * math.cos(a), 2.5 * math.sin(a), 0.6]), np.zeros(3))
                    for a in np.linspace(0, 2 * math.pi, n, endpoint=False)])
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    images = []
    for pose in c2w:
        d = np.stack([(xs - size / 2) / fl, -(ys - size / 2) / fl, -np.ones_like(xs)], -1) @ pose[:3, :3].T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        b = d @ pose[:3, 3]
        hit = b * b - (pose[:3, 3] @ pose[:3, 3] - radius**2) > 0
        rgba = np.stack([np.full_like(xs, 0.8), 0.3 + 0.4 * (d[..., 2] > 0), np.full_like(xs, 0.2), hit], -1)
        images.append(np.round(rgba * 255).astype(np.uint8))
    return images, torch.tensor(c2w, dtype=torch.float32), torch.tensor([[fl, fl, size / 2, size / 2]] * n)
