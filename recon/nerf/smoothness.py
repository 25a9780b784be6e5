"""Smooth depth where the photos are plain: an edge-aware second-order prior on small patches of the training photos.

Where a surface has little texture (a plain board, a painted patch, a dark shadow) its colour matches the photos
at many depths, and a grid field leaves it lumpy: matter forms wherever it first explains a pixel. Textured parts
are placed by the colours; plain parts need a prior. This one renders a few patches of each step's photos (a grid
of ``size`` × ``size`` rays ``stride`` pixels apart) and penalizes the second differences of their inverse depth,
which are zero for any plane (inverse depth is affine in the pixel coordinates on a plane), so slants cost nothing
and only bumps and folds do. Each difference is weighted by how plain the photo is across it (``exp(-edge_gain ·
|colour differences|)``, as monodepth's edge-aware smoothness): across an edge or a texture the colours decide
alone. Patches of masked photos lie wholly inside the object, so a silhouette's depth step is never smoothed.

Frames and units: OpenGL ``c2w`` (camera looks down -Z), intrinsics in pixels of the training images, pixel centres
at +0.5 (`recon.nerf.rays`).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from .rays import pixel_rays, ray_aabb
from .render import RadianceModel

__all__ = ["PatchSmoothness", "patch_smoothness_loss"]


def patch_smoothness_loss(depth: Tensor, forward_cos: Tensor, gray: Tensor, opacity: Tensor,
                          edge_gain: float) -> Tensor:
    """Mean edge-aware second difference of relative inverse depth over patches.

    depth (P, S, S): distances along unit rays; forward_cos (P, S, S): each ray's cosine to its camera's axis (so
    depth · cos is the depth along the axis); gray (P, S, S): the photo's brightness in [0, 1]; opacity (P, S, S):
    the render's (a difference counts by its least opaque pixel: a ray that sees nothing has no depth to smooth).
    Inverse depth is divided by each patch's mean, so the loss does not depend on the scene's scale or distance;
    the penalty is Charbonnier (L1 beyond 1e-3), so a true crease costs in proportion, not squared."""
    inv = 1.0 / (depth * forward_cos).clamp_min(1e-6)
    inv = inv / inv.mean(dim=(1, 2), keepdim=True).detach()
    terms, weights = [], []
    for dim in (1, 2):
        n = inv.shape[dim] - 2
        a, b, c = (inv.narrow(dim, k, n) for k in range(3))
        ga, gb, gc = (gray.narrow(dim, k, n) for k in range(3))
        oa, ob, oc = (opacity.narrow(dim, k, n) for k in range(3))
        second = a - 2.0 * b + c
        plain = torch.exp(-edge_gain * ((gb - ga).abs() + (gc - gb).abs()))
        seen = torch.minimum(torch.minimum(oa, ob), oc).detach().clamp(0.0, 1.0)
        terms.append((torch.sqrt(second * second + 1e-6) - 1e-3).flatten())
        weights.append((plain * seen).flatten())
    t, w = torch.cat(terms), torch.cat(weights)
    return (t * w).sum() / w.numel()


class PatchSmoothness:
    """The term of a training piece (:class:`recon.nerf.pieces.DepthPriorLoss` takes any such callable): each step,
    renders ``patches`` patches of the training photos (depth only) and returns ``{"smooth": weight · loss}``.

    Args:
        images: per photo (H, W, C) uint8 (C 3, or 4 with alpha: patches then lie wholly where alpha >= 128).
        c2w: (V, 4, 4) OpenGL camera-to-world; intrinsics: (V, 4) fl_x, fl_y, cx, cy in pixels of the images.
        aabb or near_far: where the rays start and stop, as the training rays (exactly one of them).
        size, stride: rays a patch side, and the pixels between neighbours.

    Patches are drawn from a generator seeded by (seed, step), so a resumed run draws the same ones."""

    def __init__(self, images: Sequence[np.ndarray], c2w: np.ndarray, intrinsics: np.ndarray, weight: float,
                 patches: int, *, size: int = 4, stride: int = 8, edge_gain: float = 10.0,
                 aabb: Tensor | None = None, near_far: Tensor | None = None, seed: int = 0) -> None:
        if (aabb is None) == (near_far is None):
            raise ValueError("give exactly one of aabb or near_far")
        if size < 3:
            raise ValueError(f"a patch needs at least 3 rays a side for a second difference, got {size}")
        self.weight, self.patches, self.size, self.stride = float(weight), int(patches), int(size), int(stride)
        self.edge_gain, self.seed = float(edge_gain), int(seed)
        span = (self.size - 1) * self.stride + 1
        h_max = max((image.shape[0] for image in images), default=0)
        w_max = max((image.shape[1] for image in images), default=0)
        self.gray = torch.zeros(len(images), h_max, w_max)  # one tensor, so a step gathers its patches at once
        places = []
        for v, image in enumerate(images):
            h, w = image.shape[:2]
            ok = np.zeros((h, w), bool)
            ok[: max(h - span + 1, 0), : max(w - span + 1, 0)] = True
            if image.shape[-1] == 4:  # the whole span inside the object: the window's minimum of the mask
                inside = ndimage.minimum_filter(image[..., 3] >= 128, size=span, origin=-(span // 2), mode="constant")
                ok &= inside
            ys, xs = np.nonzero(ok)
            places.append(((v * h_max + ys) * w_max + xs).astype(np.int32))  # one int a place: a capture has millions
            self.gray[v, :h, :w] = torch.from_numpy((image[..., :3].mean(axis=-1) / 255.0).astype(np.float32))
        self.places = torch.from_numpy(np.concatenate(places) if places else np.zeros(0, np.int32))
        self.c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float32)
        self.intrinsics = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float32)
        self.aabb = None if aabb is None else aabb.float()
        self.near_far = None if near_far is None else near_far.float()
        self.device = torch.device("cpu")

    def __len__(self) -> int:
        """How many patch positions the photos offer."""
        return int(self.places.shape[0])

    @property
    def starts(self) -> Tensor:
        """(N, 3) long: each patch position's photo, row and column (its top-left ray)."""
        return self._decode(self.places.long())

    def _decode(self, flat: Tensor) -> Tensor:
        _, h_max, w_max = self.gray.shape
        return torch.stack([flat // (h_max * w_max), flat // w_max % h_max, flat % w_max], dim=1)

    def to(self, device: torch.device | str) -> "PatchSmoothness":
        """Put the photos' brightness and cameras on ``device`` (patch positions are drawn on the CPU)."""
        self.device = torch.device(device)
        for name in ("gray", "c2w", "intrinsics", "aabb", "near_far"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, value.to(self.device))
        return self

    def __call__(self, model: RadianceModel, step: int, background: Tensor | None = None) -> dict[str, Tensor]:
        if len(self) == 0 or self.weight <= 0 or self.patches <= 0:
            return {}
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + step + 7)
        drawn = self.places[torch.randint(len(self), (self.patches,), generator=gen)].long()
        pick = self._decode(drawn).to(self.device)
        shape = (self.patches, self.size, self.size)
        offs = torch.arange(self.size, device=self.device) * self.stride
        view = pick[:, 0, None, None].expand(shape)
        ys = (pick[:, 1, None, None] + offs[None, :, None]).expand(shape)
        xs = (pick[:, 2, None, None] + offs[None, None, :]).expand(shape)
        v, y, x = view.reshape(-1), ys.reshape(-1), xs.reshape(-1)
        k, c2w = self.intrinsics[v], self.c2w[v]
        rays_o, rays_d = pixel_rays(c2w, k[:, 0], k[:, 1], k[:, 2], k[:, 3], x.float() + 0.5, y.float() + 0.5)
        if self.aabb is not None:
            near, far, _ = ray_aabb(rays_o, rays_d, self.aabb)
        else:
            near, far = self.near_far[v, 0], self.near_far[v, 1]
        out = model.render_rays(rays_o, rays_d, near, far, training=True,
                                background=None if background is None else background[: v.numel()], colors=False)
        cos = (rays_d * -c2w[:, :3, 2]).sum(-1)
        loss = patch_smoothness_loss(out["depth"].float().view(shape), cos.view(shape), self.gray[view, ys, xs],
                                     out["opacity"].float().view(shape), self.edge_gain)
        return {"smooth": self.weight * loss}
