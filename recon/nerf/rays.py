"""Camera rays for the fields (torch), and ray / box intersection.

The conventions (OpenGL ``c2w``, pixel centres at +0.5, intrinsics in pixels, UNIT directions so that ``t`` is in
world units) and the pixel -> ray math live in `recon.camera`; this module checks the shapes the training and
rendering loops hand it. Rays are PINHOLE: the stages undistort the photos beforehand.
"""
from __future__ import annotations

import torch
from torch import Tensor

from recon.camera import image_rays
from recon.camera import pixel_rays as _pixel_rays
from recon.nerf.kernels import ray_box_triton, use_triton
from recon.nerf.native import ray_box_native

__all__ = ["camera_rays", "pixel_rays", "ray_aabb", "ray_aabb_torch", "clip_to_box"]


def camera_rays(
    c2w: Tensor, fl_x: float, fl_y: float, cx: float, cy: float, w: int, h: int
) -> tuple[Tensor, Tensor]:
    """All rays of one image.

    Args:
        c2w: (4, 4) or (3, 4) camera-to-world (OpenGL convention); sets the device and dtype.
        fl_x, fl_y, cx, cy: pinhole intrinsics in pixels. w, h: image size in pixels.

    Returns:
        rays_o: (h, w, 3) camera centre in world coordinates (same for every pixel).
        rays_d: (h, w, 3) unit-length world directions through pixel centres; ``[j, i]`` is row j,
            column i, i.e. the layout of an (h, w, 3) image array.
    """
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"c2w must have shape (4, 4) or (3, 4), got {tuple(c2w.shape)}")
    return image_rays(c2w, fl_x, fl_y, cx, cy, w, h)


def pixel_rays(
    c2w: Tensor, fl_x: Tensor, fl_y: Tensor, cx: Tensor, cy: Tensor, px: Tensor, py: Tensor
) -> tuple[Tensor, Tensor]:
    """Rays through arbitrary pixels of many cameras (random training batches).

    Args:
        c2w: (N, 4, 4) or (N, 3, 4) camera-to-world per ray (OpenGL convention).
        fl_x, fl_y, cx, cy: (N,) intrinsics per ray (pixels).
        px, py: (N,) pixel coordinates (pixels; pass ``i + 0.5``, ``j + 0.5`` for pixel centres).
            Unlike :func:`camera_rays` these are NOT offset by 0.5 here, so sub-pixel jitter is possible.

    Returns:
        rays_o: (N, 3) world origins; rays_d: (N, 3) unit world directions.
    """
    if c2w.dim() != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"c2w must have shape (N, 4, 4) or (N, 3, 4), got {tuple(c2w.shape)}")
    n = c2w.shape[0]
    for name, v in (("fl_x", fl_x), ("fl_y", fl_y), ("cx", cx), ("cy", cy), ("px", px), ("py", py)):
        if v.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {tuple(v.shape)}")
    return _pixel_rays(c2w, fl_x, fl_y, cx, cy, px, py)


def ray_aabb(rays_o: Tensor, rays_d: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab-method intersection of rays with an axis-aligned box.

    Args:
        rays_o: (N, 3) origins; rays_d: (N, 3) directions (any length; t is in units of |rays_d|,
            world units for the unit directions made here).
        aabb: (2, 3) box ``[min_xyz, max_xyz]``.

    Returns:
        t_near: (N,) entry distance, clamped to >= 0 (an origin inside the box starts at 0).
        t_far: (N,) exit distance.
        hit: (N,) bool, True where the ray meets the box in front of the origin (t_far > t_near).
        For misses, t_near = t_far = 0 so that callers can use them without NaNs.

    Axis-parallel rays (a zero direction component) are handled without dividing by zero: on
    that axis the ray is inside the slab for all t (or never), decided by the origin alone.
    """
    if rays_o.shape != rays_d.shape or rays_o.shape[-1:] != (3,) or rays_o.dim() != 2:
        raise ValueError(f"rays_o and rays_d must both be (N, 3), got {tuple(rays_o.shape)}, {tuple(rays_d.shape)}")
    if aabb.shape != (2, 3):
        raise ValueError(f"aabb must have shape (2, 3), got {tuple(aabb.shape)}")
    if not (rays_o.requires_grad or rays_d.requires_grad):
        native = ray_box_native(rays_o, rays_d, aabb.to(rays_o))
        if native is not None:
            return native
    return ray_aabb_torch(rays_o, rays_d, aabb)


def ray_aabb_torch(rays_o: Tensor, rays_d: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`ray_aabb` in torch operations: the reference of the C pass (`recon.nerf.native.ray_box_native`), and
    the path for CUDA tensors and rays that need gradients."""
    aabb = aabb.to(rays_o)
    parallel = rays_d == 0
    t0, t1 = (aabb[:, None, :] - rays_o) / torch.where(parallel, 1.0, rays_d)  # both slabs' planes in one launch
    inside = (rays_o >= aabb[0]) & (rays_o <= aabb[1])
    always = torch.where(inside, torch.inf, -torch.inf)  # a parallel axis: in its slab for every t, or for none
    lo = torch.where(parallel, -always, torch.minimum(t0, t1))
    hi = torch.where(parallel, always, torch.maximum(t0, t1))
    t_near = lo.amax(dim=-1).clamp_min(0.0)
    t_far = hi.amin(dim=-1)
    hit = t_far > t_near
    return torch.where(hit, t_near, 0.0), torch.where(hit, t_far, 0.0), hit


def clip_to_box(rays_o: Tensor, rays_d: Tensor, near: Tensor, far: Tensor, box: Tensor,
                kernels: str = "torch") -> tuple[Tensor, Tensor]:
    """Each ray's [near, far] (N,) clipped to a box (2, 3): (t_near, t_far); a ray that misses the box gets an empty
    interval at its near end. In one C pass on a CPU (`recon.nerf.native.ray_box_native`, the same values), in one
    Triton kernel on CUDA where ``kernels`` (the fast model's `train.fast.kernels`) takes it
    (`recon.nerf.kernels.ray_box_triton`)."""
    if not (rays_o.requires_grad or rays_d.requires_grad or near.requires_grad or far.requires_grad):
        fused = ray_box_native(rays_o, rays_d, box.to(rays_o), near, far)
        if fused is None and use_triton(kernels, rays_o, rays_d, near, far):
            fused = ray_box_triton(rays_o, rays_d, box, near, far)
        if fused is not None:
            return fused[0], fused[1]
    tn, tf, hit = ray_aabb_torch(rays_o, rays_d, box)
    t_near = torch.maximum(near, tn)
    return t_near, torch.where(hit, torch.minimum(far, tf), t_near)
