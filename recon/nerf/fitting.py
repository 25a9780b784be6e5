"""What every fit to posed photos shares: their pixels as shuffled ray batches, and the learning-rate decay.

Two loops fit something to photos through a radiance field: :func:`recon.nerf.trainer.train` fits the field, and
:func:`recon.nerf.evaluate.align_pose` fits a held-out photo's camera to a frozen field. Both draw their rays from a
:class:`RayBatcher` and decay their rate with :func:`lr_at`, so the two live here rather than in either loop.

* :class:`RayBatcher` holds every training pixel (colors + which camera/pixel) and yields
  shuffled batches mixed across images, with rays computed on the fly (cheap) so that memory is
  that of the images, not of the rays. Shuffling uses its own seeded generators: same seed, same
  batches.

Camera conventions: see :mod:`recon.nerf.rays` (OpenGL c2w, pixel centres, pinhole, unit rays_d).
"""
from __future__ import annotations

from typing import Any, Sequence

import torch
from torch import Tensor

from .kernels import pixel_rays_triton, use_triton
from .native import pixel_rays_native
from .rays import pixel_rays, ray_aabb

__all__ = ["RayBatcher", "lr_at"]


def _as_weights(mask: Tensor | Any) -> Tensor:
    """An ``empty`` mask as uint8 weights 0..255: bool masks as 0 or 255, float ones in [0, 1] rounded to 1/255."""
    m = torch.as_tensor(mask)
    if m.dtype == torch.bool:
        return m.to(torch.uint8) * 255
    return (m.float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


class RayBatcher:
    """All training pixels of a set of posed images, served as shuffled ray batches.

    Args:
        images: (n, H, W, C) tensor or a list of (H_i, W_i, C) tensors; C = 3 (RGB) or 4 (RGBA,
            straight alpha); float in [0, 1] or uint8 (kept as uint8 to save memory).
        c2w: (n, 4, 4) or (n, 3, 4) camera-to-world, OpenGL convention, scene frame.
        intrinsics: (n, 4) ``fl_x, fl_y, cx, cy`` in pixels of these images.
        aabb: (2, 3) scene box; rays get near/far from it. Either this or ``near_far``.
        near_far: (n, 2) or (2,) per-image (or global) near and far distances along the unit-length rays
            (world units; not depths along the optical axis).
        background: (3,) color behind the scene: RGBA pixels are composited onto it, and the
            model renders leftover transmittance with it.
        random_background: RGBA only: composite each ray onto a fresh random color (given to the
            model too), which stops the model from painting the background into the density.
        empty: per image an (H, W) mask (tensor or array) of pixels known to see nothing up to ``far`` (the sky,
            `recon.capture.sky`, or the transparent pixels of masked photos): bool, or a float weight in [0, 1] of
            how surely each pixel sees nothing (kept to 1/255); each batch then carries ``empty (B,)`` (float)
            for the piece :class:`recon.nerf.pieces.EmptyRays`.
        drop_missed: with ``aabb``, leave out pixels whose rays miss the box (they can only show
            background); the count is in ``n_dropped``.
        seed: seeds the shuffling and random-background generators.
        device: where batches are produced (default: the images' device).
        kernels: the fast model's ``train.fast.kernels``: on CUDA, "triton" or "auto" make a batch's rays in one
            Triton kernel where :func:`recon.nerf.kernels.use_triton` takes them (a CPU makes them in C).

    Batches (:meth:`next_batch`) are dicts of ``rays_o, rays_d (B, 3)``, ``near, far (B,)``,
    ``rgb (B, 3)`` target, ``background (B, 3)``, ``image (B,)`` (long: which image each ray comes
    from, for per-photo appearance) and, given ``empty``, ``empty (B,)``; every pixel is used once per epoch.
    """

    def __init__(
        self,
        images: Tensor | Sequence[Tensor],
        c2w: Tensor,
        intrinsics: Tensor,
        *,
        aabb: Tensor | None = None,
        near_far: Tensor | None = None,
        background: Tensor | Sequence[float] = (1.0, 1.0, 1.0),
        random_background: bool = False,
        empty: Sequence[Tensor] | None = None,
        drop_missed: bool = True,
        seed: int = 0,
        device: torch.device | str | None = None,
        kernels: str = "torch",
    ) -> None:
        imgs = list(images) if not isinstance(images, Tensor) else list(images.unbind(0))
        n = len(imgs)
        if n == 0:
            raise ValueError("RayBatcher needs at least one image")
        self.device = torch.device(device) if device is not None else imgs[0].device
        chans = {im.shape[-1] for im in imgs}
        if any(im.dim() != 3 for im in imgs) or not chans <= {3, 4} or len(chans) != 1:
            raise ValueError(f"images must all be (H, W, 3) or all (H, W, 4); got shapes {sorted({tuple(i.shape) for i in imgs})}")
        self.has_alpha = chans == {4}
        if c2w.shape[0] != n or c2w.shape[1:] not in ((4, 4), (3, 4)):
            raise ValueError(f"c2w must be ({n}, 4, 4) for {n} images, got {tuple(c2w.shape)}")
        if intrinsics.shape != (n, 4):
            raise ValueError(f"intrinsics must be ({n}, 4) = fl_x, fl_y, cx, cy per image, got {tuple(intrinsics.shape)}")
        if (aabb is None) == (near_far is None):
            raise ValueError("give exactly one of aabb (scene box) or near_far (per-image near/far)")
        self.pixels = torch.cat([im.reshape(-1, im.shape[-1]) for im in imgs]).to(self.device)
        if self.pixels.is_floating_point():
            bad = ~torch.isfinite(self.pixels).all(-1)
            if bad.any():
                first = int(bad.nonzero()[0])
                raise ValueError(f"images contain NaN/inf values (first at flat pixel {first}); fix the inputs")
        sizes = torch.tensor([[im.shape[1], im.shape[0]] for im in imgs], device=self.device)  # (n, 2) = W, H
        self.sizes = sizes
        self._widths = sizes[:, 0].contiguous()
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long, device=self.device), torch.cumsum(sizes[:, 0] * sizes[:, 1], 0)])
        self.c2w = c2w[:, :3, :4].to(self.device, torch.float32)
        self.intrinsics = intrinsics.to(self.device, torch.float32)
        self.aabb = None if aabb is None else aabb.to(self.device, torch.float32)
        if near_far is not None:
            nf = near_far.to(self.device, torch.float32)
            self.near_far = (nf.expand(n, 2) if nf.shape == (2,) else nf).contiguous()  # as a batch's C pass reads it
            if self.near_far.shape != (n, 2):
                raise ValueError(f"near_far must be (2,) or ({n}, 2), got {tuple(near_far.shape)}")
        else:
            self.near_far = None
        self.empty: Tensor | None = None
        if empty is not None:
            if len(empty) != n or any(tuple(m.shape) != tuple(im.shape[:2]) for m, im in zip(empty, imgs, strict=True)):
                raise ValueError("empty must hold one (H, W) mask per image, each the size of its image")
            self.empty = torch.cat([_as_weights(m).reshape(-1) for m in empty]).to(self.device)
        self.background = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        self.random_background = random_background and self.has_alpha
        self.seed = seed
        self.kernels = kernels
        self.valid: Tensor | None = None
        total = int(self.offsets[-1])
        if self.aabb is not None and drop_missed:
            keep = torch.cat([self._rays(torch.arange(s, min(s + 2**20, total), device=self.device))[4]
                              for s in range(0, total, 2**20)])
            self.valid = keep.nonzero().squeeze(-1)
        self.n_rays = total if self.valid is None else int(self.valid.numel())
        self.n_dropped = total - self.n_rays
        if self.n_rays == 0:
            raise ValueError("no training ray meets the scene box: check the poses and the aabb")
        # each epoch's shuffle is drawn where the batches are made: on a GPU a CPU's draw of millions of indices would
        # leave the card idle at every epoch's start (a CPU draws the same order as before; a GPU its own)
        self._perm_gen = torch.Generator(device=self.device if self.device.type == "cuda" else "cpu").manual_seed(seed)
        self._bg_gen = torch.Generator(device=self.device).manual_seed(seed + 1)
        self._new_epoch()

    # -- pixel bookkeeping
    def image_index(self, flat: Tensor) -> Tensor:
        """Flat pixel indices (B,) -> the index (B,) long of the image each pixel belongs to."""
        return torch.searchsorted(self.offsets, flat, right=True) - 1

    def _rays(self, flat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Flat pixel indices (B,) -> rays_o, rays_d (B, 3), near, far (B,), hit (B,) bool, image (B,) long; in one C
        pass on a CPU (`recon.nerf.native.pixel_rays_native`), one Triton kernel on CUDA where ``kernels`` (the fast
        model's `train.fast.kernels`) takes them (`recon.nerf.kernels.pixel_rays_triton`), else in torch
        (:meth:`_rays_torch`, their reference)."""
        args = (flat, self.offsets, self._widths, self.c2w, self.intrinsics, self.aabb, self.near_far)
        native = pixel_rays_native(*args)
        if native is not None:
            return native
        if use_triton(self.kernels, self.c2w):
            return pixel_rays_triton(*args)
        return self._rays_torch(flat)

    def _rays_torch(self, flat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        img = self.image_index(flat)
        local = flat - self.offsets[img]
        w = self.sizes[img, 0]
        px = (local % w).float() + 0.5
        py = torch.div(local, w, rounding_mode="floor").float() + 0.5
        k = self.intrinsics[img]
        o, d = pixel_rays(self.c2w[img], k[:, 0], k[:, 1], k[:, 2], k[:, 3], px, py)
        if self.aabb is not None:
            near, far, hit = ray_aabb(o, d, self.aabb)
        else:
            near, far = self.near_far[img, 0], self.near_far[img, 1]
            hit = far > near
        return o, d, near, far, hit, img

    def _new_epoch(self) -> None:
        self._epoch_gen_state = self._perm_gen.get_state()
        # kept where the pixels are: a batch's indices copied to a GPU each step would wait for its queued work
        self._perm = torch.randperm(self.n_rays, generator=self._perm_gen, device=self._perm_gen.device)
        self._cursor = 0

    def _take(self, b: int) -> Tensor:
        parts, need = [], b
        while need > 0:
            if self._cursor >= self.n_rays:
                self._new_epoch()
            chunk = self._perm[self._cursor : self._cursor + need]
            self._cursor += chunk.numel()
            need -= chunk.numel()
            parts.append(chunk)
        idx = torch.cat(parts) if len(parts) > 1 else parts[0]
        return idx if self.valid is None else self.valid[idx]

    def next_batch(self, batch_rays: int) -> dict[str, Tensor]:
        """The next ``batch_rays`` rays of the shuffled epoch (crossing into the next epoch as needed)."""
        flat = self._take(batch_rays)
        o, d, near, far, _, img = self._rays(flat)
        px = self.pixels[flat]
        px = px.float() / 255.0 if not px.is_floating_point() else px.float()
        if self.random_background:
            bg = torch.rand((flat.numel(), 3), generator=self._bg_gen, device=self.device)
        else:
            bg = self.background.expand(flat.numel(), 3)
        rgb = px[:, :3]
        if self.has_alpha:
            a = px[:, 3:4]
            rgb = rgb * a + bg * (1.0 - a)
        batch = {"rays_o": o, "rays_d": d, "near": near, "far": far, "rgb": rgb, "background": bg,
                 "image": img}
        if self.empty is not None:
            batch["empty"] = self.empty[flat].float() / 255.0
        return batch

    def state_dict(self) -> dict[str, Any]:
        """Position in the shuffled stream (small: the permutation is regenerated from its seed state)."""
        return {"epoch_gen_state": self._epoch_gen_state.clone(), "cursor": self._cursor,
                "bg_gen_state": self._bg_gen.get_state().clone(), "n_rays": self.n_rays}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue the stream exactly where :meth:`state_dict` was taken (same images and seed)."""
        if state["n_rays"] != self.n_rays:
            raise ValueError(f"batcher state is for {state['n_rays']} rays, this batcher has {self.n_rays}: different data")
        self._perm_gen.set_state(state["epoch_gen_state"])
        self._new_epoch()
        self._cursor = int(state["cursor"])
        self._bg_gen.set_state(state["bg_gen_state"])


def lr_at(step: int, steps: int, lr: float, lr_final: float | None, fraction: float | None = None) -> float:
    """Exponential decay from ``lr`` at step 0 to ``lr_final`` at ``steps`` (constant if lr_final is None).

    ``fraction`` (of the training done, e.g. of a time budget) overrides ``step / steps`` when larger.
    """
    if lr_final is None or steps <= 0:
        return lr
    return lr * (lr_final / lr) ** training_done(step, steps, fraction)


def training_done(step: int, steps: int, fraction: float | None = None) -> float:
    """The share of training done, 0 to 1: ``step / steps``, or ``fraction`` (of a time budget spent) when larger."""
    done = min(step, steps) / steps if steps > 0 else 0.0
    if fraction is not None:
        done = max(done, fraction)
    return min(max(done, 0.0), 1.0)
