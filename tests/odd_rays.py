"""Rays and photo batches that reach the corners of ray/box and pixel-to-ray code: axis-parallel directions (+0 and
-0), origins on the box's faces, inside and outside it, NaN and infinite components; photos of different sizes with
their first and last pixels. Shared by tests/test_native_march.py and tests/test_triton_kernels.py, which hold the C
passes and the Triton kernels to the torch code (test modules never import each other)."""
from __future__ import annotations

import torch
from torch import Tensor

from recon.camera import look_at
from recon.nerf.fitting import RayBatcher

BOX = torch.tensor([[-1.0, -0.5, -1.0], [1.0, 1.5, 0.25]])


def odd_rays(n: int = 3000, seed: int = 0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """rays_o, rays_d (n, 3) and near, far (n,) against :data:`BOX`, every kind of ray several times."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g) * 2
    d = torch.randn(n, 3, generator=g)
    d[::7, 0] = 0.0
    d[::11, 1] = -0.0
    d[::13] = 0.0
    o[::5, 2] = BOX[1, 2]  # on a face
    o[::9] = o[::9] * 0.1  # inside
    o[::17, 0] = BOX[0, 0]
    o[::19] = float("nan")
    d[::23, 1] = float("nan")
    d[::29, 0] = float("inf")
    d[::31] = d[::31] * 1e-30  # divisions that overflow to infinity
    near = torch.rand(n, generator=g)
    far = near + 4 * torch.rand(n, generator=g)
    near[::37] = float("nan")
    return o, d, near, far


def stacked_batcher(box: bool) -> RayBatcher:
    """A batcher over five photos of different sizes looking at the origin, with a scene box or with near and far."""
    sizes = [(30, 40), (25, 33), (40, 40), (7, 9), (31, 41)]
    g = torch.Generator().manual_seed(3)
    images = [torch.rand(h, w, 3, generator=g) for h, w in sizes]
    eyes = [(0.0, 0.5, 3.0), (2.5, 1.0, 1.0), (-2.0, -1.5, 2.0), (0.3, 3.0, 0.2), (1.0, 0.0, -2.5)]
    c2w = torch.stack([torch.as_tensor(look_at(e, (0.0, 0.0, 0.0)), dtype=torch.float32) for e in eyes])
    intrinsics = torch.tensor([[w * 1.2, w * 1.25, w / 2 + 0.3, h / 2 - 0.2] for h, w in sizes])
    if box:
        return RayBatcher(images, c2w, intrinsics, aabb=BOX, drop_missed=False)
    return RayBatcher(images, c2w, intrinsics, near_far=torch.tensor([[0.5, 6.0], [0.1, 2.0], [1.0, 1.0], [0.2, 3.0],
                                                                       [0.0, 9.0]]))
