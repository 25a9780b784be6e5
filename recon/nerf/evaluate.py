"""Using a trained field without training it: render a camera, and score held-out photos fairly.

The training loop (:mod:`recon.nerf.trainer`) only fits; everything that reads a trained field lives here, so
scoring a scene, the Python API, the viewer and the mesh stage never import the trainer:

* :func:`render_image` renders one camera in chunks under ``inference_mode``;
* the held-out protocols, which keep the scored pixels from shaping what is fitted before scoring: a field
  trained with per-photo appearance gets each held-out photo's colour transform fitted on the photo's left half
  (:func:`held_out_right_half`, :data:`HELD_OUT_PROTOCOL`); a field trained with refined poses gets each held-out
  photo's pose fitted to the frozen field on its left half (:func:`align_pose`, :data:`POSE_PROTOCOL`); either
  way only the right half (:func:`left_right_split`) is scored.

Camera conventions: see :mod:`recon.nerf.rays` (OpenGL c2w, pixel centres, pinhole, unit rays_d).
"""
from __future__ import annotations

import itertools
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .appearance import apply_affine, fit_affine
from .fitting import RayBatcher, lr_at
from .pose_refine import PoseRefinement
from .rays import camera_rays, ray_aabb
from .render import RadianceModel

__all__ = [
    "ALIGN_LR",
    "ALIGN_STEPS",
    "HELD_OUT_PROTOCOL",
    "POSE_PROTOCOL",
    "align_pose",
    "held_out_right_half",
    "left_right_split",
    "render_image",
]


# ----------------------------------------------------------------------------- rendering
CUDA_CHUNK_GIB = 5.0
"""On CUDA a render chunk grows by the model's ``render_chunk`` rays for each this many GiB of the card's memory (up
to 16×: the whole of a 400² view at once on a 80 GB card): each chunk launches the marcher's and the field's kernels
again, so on a GPU larger chunks render a view faster (the chunk sweep in benchmarks/results/gpu_check.json)."""


def default_render_chunk(model: torch.nn.Module, device: torch.device) -> int:
    """Rays a chunk when rendering a view: 8192, or the model's ``render_chunk`` where it has one (the fast model:
    packed samples, only where the occupancy grid has matter), scaled up on CUDA (:data:`CUDA_CHUNK_GIB`)."""
    base = getattr(model, "render_chunk", None)
    if base is None or device.type != "cuda":
        return int(base or 8192)
    gib = torch.cuda.get_device_properties(device).total_memory / 2**30
    return base * max(1, min(16, int(gib // CUDA_CHUNK_GIB)))


def render_image(
    model: RadianceModel,
    c2w: Tensor,
    intrinsics: Tensor | Sequence[float],
    h: int,
    w: int,
    chunk: int | None = None,
    *,
    aabb: Tensor | None = None,
    near: float | None = None,
    far: float | None = None,
    background: Tensor | Sequence[float] = (1.0, 1.0, 1.0),
    autocast: torch.dtype | None = None,
    colors: bool = True,
) -> dict[str, Tensor]:
    """Render one camera, ``chunk`` rays at a time (default: :func:`default_render_chunk`), under
    ``inference_mode`` in eval mode.

    Args:
        c2w: (4, 4) or (3, 4) camera-to-world (OpenGL); intrinsics: fl_x, fl_y, cx, cy (pixels).
        aabb: (2, 3) scene box giving near/far per ray (rays missing it show the background
            without running the model); or give ``near`` and ``far`` distances.
        autocast: mixed-precision dtype for the model (see :class:`recon.nerf.trainer.TrainStep`), or None.
        colors: False for depth and opacity only (rgb is then the background where the model skips its colour
            work: :meth:`RadianceModel.render_rays`).

    Returns dict: rgb (h, w, 3), depth (h, w) (0 where the ray misses the box), opacity (h, w).
    """
    first = next(itertools.chain(model.parameters(), model.buffers()), None)
    device = first.device if first is not None else torch.device("cpu")
    k = [float(v) for v in (intrinsics.tolist() if isinstance(intrinsics, Tensor) else intrinsics)]
    o, d = camera_rays(c2w.to(device, torch.float32), *k, w, h)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    if aabb is not None:
        t0, t1, hit = ray_aabb(o, d, aabb.to(device, torch.float32))
    elif near is not None and far is not None:
        t0, t1 = torch.full_like(o[:, 0], near), torch.full_like(o[:, 0], far)
        hit = torch.ones_like(t0, dtype=torch.bool)
    else:
        raise ValueError("render_image needs aabb or both near and far")
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    rgb = bg.expand(h * w, 3).clone()
    depth = torch.zeros(h * w, device=device)
    opacity = torch.zeros(h * w, device=device)
    idx = hit.nonzero().squeeze(-1)
    chunk = chunk or default_render_chunk(model, device)
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode(), torch.autocast(device.type, dtype=autocast or torch.bfloat16, enabled=autocast is not None):
            for s in range(0, idx.numel(), chunk):
                i = idx[s : s + chunk]
                out = model.render_rays(o[i], d[i], t0[i], t1[i], training=False, background=bg, colors=colors)
                rgb[i], depth[i], opacity[i] = out["rgb"].float(), out["depth"].float(), out["opacity"].float()
    finally:
        model.train(was_training)
    return {"rgb": rgb.view(h, w, 3), "depth": depth.view(h, w), "opacity": opacity.view(h, w)}


# ----------------------------------------------------------------------------- held-out protocols
def left_right_split(width: int) -> tuple[slice, slice]:
    """Columns of the half a held-out photo's transform is fitted on (left) and of the half scored (right)."""
    half = width // 2
    return slice(0, half), slice(half, width)


HELD_OUT_PROTOCOL = ("each held-out photo's colour transform is fitted (closed form) on its left half and PSNR/SSIM "
                     "are measured on its right half only (NeRF-W), so no scored pixel shapes the transform")


def held_out_right_half(pred: np.ndarray, target: np.ndarray, opacity: np.ndarray | None = None,
                        background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(render, photo) of the right half of a held-out view, the render through the transform fitted on the left.

    pred, target: (H, W, 3); opacity (H, W) and background (3,) for photos with alpha (only the field's part is
    transformed). Only the left half's pixels enter the fit (see :func:`left_right_split`).
    """
    left, right = left_right_split(pred.shape[1])
    op_l = None if opacity is None else opacity[:, left]
    a, b = fit_affine(pred[:, left], target[:, left], opacity=op_l, background=background)
    op_r = None if opacity is None else opacity[:, right]
    return apply_affine(np.ascontiguousarray(pred[:, right]), a, b, opacity=op_r, background=background), target[:, right]


POSE_PROTOCOL = ("each held-out photo's pose is fitted to the frozen field on its left half (the training poses were "
                 "refined) and PSNR/SSIM are measured on its right half only, so no scored pixel shapes the pose")


ALIGN_STEPS = 100
"""Updates that fit a held-out photo's pose to the frozen field (its rate decays from ALIGN_LR to 1/40 of it)."""

ALIGN_LR = 2e-3
"""Adam's rate for those updates (radians, scene units): up to ~0.1 rad over the fit, far more than SfM is off."""


def align_pose(
    model: RadianceModel,
    image: Tensor,
    c2w: Tensor,
    intrinsics: Sequence[float],
    *,
    aabb: Tensor | None = None,
    near_far: tuple[float, float] | None = None,
    background: Tensor | Sequence[float] = (1.0, 1.0, 1.0),
    steps: int = ALIGN_STEPS,
    batch_rays: int = 1024,
    lr: float = ALIGN_LR,
    seed: int = 0,
) -> Tensor:
    """A photo's camera (4, 4) fitted to the frozen field on the pixels of ``image`` (H, W, C): for scoring a held-out
    photo of a field whose training poses were refined (BARF's protocol), since the field's frame then differs from the
    given poses by the photos' own pose errors. Pass only the columns that will not be scored (a left half, cropped
    from x = 0, keeps the intrinsics). The model's parameters are left untouched."""
    device = c2w.device
    k = torch.tensor([list(intrinsics)], dtype=torch.float32, device=device)
    batcher = RayBatcher([image.to(device)], c2w[None, :3, :4].float(), k, aabb=aabb,
                         near_far=None if aabb is not None else torch.tensor(near_far, dtype=torch.float32),
                         background=background, seed=seed, device=device)
    refine = PoseRefinement(1).to(device)
    opt = torch.optim.Adam(refine.parameters(), lr=lr)
    frozen = [(p, p.requires_grad) for p in model.parameters()]
    was_training = model.training
    model.eval()
    try:
        for p, _ in frozen:
            p.requires_grad_(False)
        with torch.enable_grad():
            for step in range(steps):
                for g in opt.param_groups:
                    g["lr"] = lr_at(step, steps, lr, lr / 40.0)
                batch = refine.correct_batch(batcher.next_batch(batch_rays), batcher.aabb)
                out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"],
                                        training=False, background=batch["background"])
                loss = F.mse_loss(out["rgb"].float(), batch["rgb"])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
    finally:
        for p, flag in frozen:
            p.requires_grad_(flag)
        model.train(was_training)
    full = torch.eye(4, dtype=torch.float32, device=device)
    full[:3, :4] = c2w[:3, :4].float()
    return refine.corrected_c2w(full[None])[0]
