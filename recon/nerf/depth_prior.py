"""Sparse-depth supervision from structure-from-motion points (DS-NeRF, Deng et al. 2022).

With few photos the colours alone leave the geometry ambiguous: a field can explain 15 views with
floaters or a surface at the wrong depth. SfM already triangulated points on the surface; each point a
photo observes gives a ray (from the camera centre through the point) whose termination depth is known
up to the point's uncertainty. This module turns those points into depth targets and scores the
field's rendered depth against them.

* :func:`sparse_depth_targets` — per-photo rays through the points it observes, target distance
  along the unit ray and its standard deviation from the reprojection error and triangulation angle.
* :func:`depth_loss` — robust, uncertainty-weighted loss on the rendered (expected) depth.
* :class:`DepthPrior` — a callable that renders a few target rays per step; training takes it as the
  piece :class:`recon.nerf.pieces.DepthPriorLoss`.

Frames and units: OpenGL ``c2w`` (camera looks down -Z), intrinsics in pixels of the training images,
distances along unit-length rays in scene units (`recon.capture.scene.RAY_DISTANCE`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from recon.camera import MIN_KEYPOINT_ERROR_PX, MIN_TRIANGULATION_DEG, project, triangulation_angles

from .rays import ray_aabb
from .render import RadianceModel

__all__ = ["DepthTargets", "DepthPrior", "depth_loss", "sparse_depth_targets"]



@dataclass
class DepthTargets:
    """Rays whose termination distance is known: rays_o, rays_d (M, 3) unit; depth, sigma (M,) along the ray;
    view (M,) index of the photo each ray comes from."""

    rays_o: Tensor
    rays_d: Tensor
    depth: Tensor
    sigma: Tensor
    view: Tensor

    def __len__(self) -> int:
        return int(self.depth.shape[0])


def sparse_depth_targets(
    points: np.ndarray,
    visible: Sequence[np.ndarray],
    c2w: np.ndarray,
    intrinsics: np.ndarray,
    sizes: np.ndarray,
    pixel_error: np.ndarray | float,
    *,
    alpha: Sequence[np.ndarray | None] | None = None,
    min_sigma: float = 0.0,
) -> DepthTargets:
    """Depth targets from the sparse points each training photo observes.

    Args:
        points: (P, 3) sparse points, scene frame.
        visible: per photo (V of them), indices into points that the photo observes (its SfM track entries).
        c2w: (V, 4, 4) OpenGL camera-to-world; intrinsics (V, 4) fl_x, fl_y, cx, cy and sizes (V, 2) w, h,
            in pixels of the training images.
        pixel_error: (P,) or scalar reprojection error of the points, in training pixels (floored at
            MIN_KEYPOINT_ERROR_PX).
        alpha: per photo an (H, W) uint8 mask (>= 128 = object) or None: points that project onto the
            masked-out background are left out (those rays train as empty).
        min_sigma: floor on the depth uncertainty (e.g. the field's voxel: it cannot place a surface finer).

    The ray to a point p from a camera at o is d = (p - o) / |p - o| with target |p - o|: it passes through
    the point's projection, where the keypoint was. Its uncertainty is that of triangulation,
    sigma = |p - o| · e / (f · sin θ) (e: reprojection error in pixels, f: focal in pixels, θ: the widest
    angle between the point's observing rays, floored at MIN_TRIANGULATION_DEG). Points behind a camera or outside
    its image are skipped.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    c2w = np.asarray(c2w, np.float64)
    err = np.broadcast_to(np.maximum(np.asarray(pixel_error, np.float64), MIN_KEYPOINT_ERROR_PX), (len(pts),))
    theta = np.maximum(triangulation_angles(pts, c2w[:, :3, 3], visible), math.radians(MIN_TRIANGULATION_DEG))
    out: dict[str, list[np.ndarray]] = {"o": [], "d": [], "depth": [], "sigma": [], "view": []}
    for v, idx in enumerate(visible):
        idx = np.asarray(idx, np.int64)
        if idx.size == 0:
            continue
        fx, fy, cx, cy = np.asarray(intrinsics[v], np.float64)
        w, h = np.asarray(sizes[v])
        uv, z = project(pts[idx], c2w[v], (fx, fy, cx, cy))
        u, r = uv[:, 0], uv[:, 1]
        ok = (z > 1e-9) & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        if alpha is not None and alpha[v] is not None:
            a = alpha[v]
            ui, ri = np.clip(u, 0, w - 1).astype(np.int64), np.clip(r, 0, h - 1).astype(np.int64)
            ok &= np.where(ok, a[ri, ui] >= 128, False)
        idx = idx[ok]
        ray = pts[idx] - c2w[v, :3, 3]
        dist = np.linalg.norm(ray, axis=1)
        out["o"].append(np.broadcast_to(c2w[v, :3, 3], ray.shape))
        out["d"].append(ray / dist[:, None])
        out["depth"].append(dist)
        out["sigma"].append(np.maximum(dist * err[idx] / (0.5 * (fx + fy) * np.sin(theta[idx])), min_sigma))
        out["view"].append(np.full(len(idx), v))
    cat = {k: (np.concatenate(v) if v else np.zeros((0, 3) if k in "od" else 0)) for k, v in out.items()}
    f32 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)  # noqa: E731
    return DepthTargets(f32(cat["o"]).reshape(-1, 3), f32(cat["d"]).reshape(-1, 3), f32(cat["depth"]),
                        f32(cat["sigma"]), torch.as_tensor(cat["view"], dtype=torch.long))


def depth_loss(depth: Tensor, target: Tensor, sigma: Tensor) -> Tensor:
    """Mean robust loss of rendered depths (N,) against targets (N,) with standard deviations sigma (N,).

    rho(r) = sqrt(1 + r²) - 1 with r = (depth - target) / sigma: a Gaussian's negative log-likelihood
    (r² / 2) within one sigma, growing only linearly beyond, so a wrong SfM match cannot dominate, and its
    gradient never exceeds 1 / sigma. Zero exactly when the depth equals the target.
    """
    r2 = ((depth - target) / sigma) ** 2
    return (r2 / (torch.sqrt(1.0 + r2) + 1.0)).mean()  # = sqrt(1 + r²) - 1 without cancellation at small r


class DepthPrior:
    """The term of the training piece :class:`recon.nerf.pieces.DepthPriorLoss`: each step, renders ``rays`` of
    the depth targets and returns ``{"depth": weight · depth_loss}``.

    Rays are drawn from a generator seeded by (seed, step), so a resumed run draws the same ones. near/far
    come from the box (bounded scenes) or the photo's own near/far (``near_far`` (V, 2)); targets outside
    them are dropped at construction.
    """

    def __init__(self, targets: DepthTargets, weight: float, rays: int, *, aabb: Tensor | None = None,
                 near_far: Tensor | None = None, seed: int = 0) -> None:
        if (aabb is None) == (near_far is None):
            raise ValueError("give exactly one of aabb or near_far")
        if aabb is not None:
            near, far, hit = ray_aabb(targets.rays_o, targets.rays_d, aabb.float().cpu())
        else:
            nf = near_far.float().cpu()[targets.view]
            near, far = nf[:, 0], nf[:, 1]
            hit = far > near
        keep = hit & (targets.depth > near) & (targets.depth < far)
        self.rays_o, self.rays_d = targets.rays_o[keep], targets.rays_d[keep]
        self.depth, self.sigma = targets.depth[keep], targets.sigma[keep]
        self.near, self.far = near[keep], far[keep]
        self.weight, self.rays, self.seed = float(weight), int(rays), int(seed)
        self.dropped = len(targets) - int(keep.sum())

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    def to(self, device: torch.device | str) -> "DepthPrior":
        for name in ("rays_o", "rays_d", "depth", "sigma", "near", "far"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    def __call__(self, model: RadianceModel, step: int, background: Tensor | None = None) -> dict[str, Tensor]:
        if len(self) == 0 or self.weight <= 0:
            return {}
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        i = torch.randint(len(self), (min(self.rays, len(self)),), generator=gen).to(self.depth.device)
        bg = None if background is None else background[: i.numel()]
        out = model.render_rays(self.rays_o[i], self.rays_d[i], self.near[i], self.far[i], training=True, background=bg,
                                colors=False)  # the loss reads depth only
        return {"depth": self.weight * depth_loss(out["depth"].float(), self.depth[i], self.sigma[i])}
