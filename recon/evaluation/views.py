"""Photos as views (image at training size, pose, intrinsics), rendering a view, and scoring renders.

One home for what train, mesh and novel views share: `load_views` reads, downscales and undistorts photos
the same way everywhere, and `evaluate` gives the numbers both training and `recon eval` report.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recon.capture.images import read_image, read_mask, undistort
from recon.capture.scene import Frame, Scene


@dataclass
class View:
    """One photo at training resolution, ready for rays: image (H, W, C) uint8, pose, intrinsics."""

    name: str
    image: np.ndarray
    c2w: np.ndarray
    intrinsics: tuple[float, float, float, float]
    near: float
    far: float

    @property
    def hw(self) -> tuple[int, int]:
        return self.image.shape[0], self.image.shape[1]


def load_view(scene: Scene, frame: Frame, max_side: int, keep_alpha: bool) -> View:
    """Read, downscale and undistort one photo; intrinsics scaled to the new size."""
    image = read_image(scene.image_path(frame), max_side=max_side)
    h, w = image.shape[:2]
    if frame.mask_path:  # the mask becomes the alpha channel: what it calls background trains as background
        image = np.concatenate([image[..., :3], read_mask(scene.mask_file(frame), (w, h))[..., None]], axis=-1)
    fl_x, fl_y, cx, cy = frame.intrinsics_at(w, h)
    image = undistort(image, fl_x, fl_y, cx, cy, frame.distortion, frame.camera_model)
    if not keep_alpha:
        image = image[..., :3]
    elif image.shape[-1] == 3:
        image = np.concatenate([image, np.ones_like(image[..., :1])], axis=-1)
    return View(frame.stem, np.round(np.clip(image, 0, 1) * 255).astype(np.uint8), frame.c2w, (fl_x, fl_y, cx, cy), frame.near or 0.0, frame.far or 0.0)


def load_views(scene: Scene, frames: list[Frame], max_side: int, report: Any = None, what: str = "photos",
               sides: dict[str, int] | None = None) -> list[View]:
    """Every frame's photo at training resolution, with a progress bar when a reporter is given."""
    views = []
    with report.task(f"loading {what}", total=len(frames)) if report else contextlib.nullcontext() as bar:
        for f in frames:
            views.append(load_view(scene, f, (sides or {}).get(f.name, max_side), scene.has_alpha))
            if bar is not None:
                bar.advance()
    return views


def _border_pixels(views: list[View]) -> np.ndarray:
    """The photos' outer pixel rows/columns (N, 3), as floats in [0, 1]."""
    border = np.concatenate([np.concatenate([v.image[0], v.image[-1], v.image[:, 0], v.image[:, -1]])[:, :3] for v in views])
    return border.astype(np.float32) / 255.0


def border_color(views: list[View]) -> np.ndarray:
    """Median color of the photos' outer pixel rows/columns: the backdrop of a typical object capture."""
    return np.median(_border_pixels(views), axis=0)


BACKDROP_TOLERANCE = 0.04
"""A pixel is backdrop when no channel differs from the backdrop's colour by more than this (the generator's white
on JPEG: every border pixel within 0.02; the fox's room: 4 % of its border pixels within 0.04)."""
PLAIN_BACKDROP_FRACTION = 0.9
"""The photos stand on a plain backdrop when at least this fraction of their border pixels are backdrop."""


def plain_backdrop(views: list[View], tolerance: float = BACKDROP_TOLERANCE) -> tuple[np.ndarray, float]:
    """(the border colour, the fraction of border pixels within `tolerance` of it in every channel)."""
    border = _border_pixels(views)
    color = np.median(border, axis=0)  # border_color's, from the pixels in hand
    return color, float((np.abs(border - color).max(axis=-1) <= tolerance).mean())


def key_backdrop(image: np.ndarray, color: np.ndarray, tolerance: float = BACKDROP_TOLERANCE) -> np.ndarray:
    """RGBA uint8 (H, W, 4) from an RGB photo (H, W, 3) uint8 on a plain backdrop of `color` (3,) in [0, 1].

    Alpha ramps from 0 where no channel is more than `tolerance` from the backdrop to 1 at three times that, and
    the colour is un-mixed (straight alpha: rgb·a + color·(1 - a) is the photo again), so compositing onto the
    backdrop reproduces the photo while compositing onto random colours says where the object is not.
    Every pixel that differs from the backdrop more than the ramp is object: nothing of the object is lost, at
    the price of the object's own backdrop-coloured parts (none on the generator's captures)."""
    p = image[..., :3].astype(np.float32) / 255.0
    c = np.asarray(color, np.float32)
    a = np.clip((np.abs(p - c).max(axis=-1) - tolerance) / (2.0 * tolerance), 0.0, 1.0)[..., None]
    rgb = np.where(a > 0, (p - (1.0 - a) * c) / np.maximum(a, 1e-6), c)
    return np.round(np.clip(np.concatenate([rgb, a], axis=-1), 0.0, 1.0) * 255).astype(np.uint8)


MAX_RAYS_A_SIDE = 4
"""The most rays along each side of a pixel when a view is coarser than the training photos (16 a pixel): a view
that much coarser is already box-filtered closely, and each step up costs the square of it in rays."""


def training_focal(frames: list[Frame], max_side: int) -> float:
    """The training photos' median focal length in pixels at the size training reads them (`read_image` scales a
    photo down to `max_side` on its longest side)."""
    return float(np.median([f.fl_x * min(1.0, max_side / max(f.w, f.h)) for f in frames]))


def rays_a_side(view: View, focal: float) -> int:
    """k, for k×k rays a pixel: how many times coarser the view's pixels are than the training photos' (focal lengths
    `focal` against the view's), to the nearest whole number, 1 to MAX_RAYS_A_SIDE.

    A field trained on photos at one pixel size holds detail down to that size; one ray through each centre of a
    coarser view samples that detail instead of averaging it, as the coarser photo's pixel does (a camera's, and
    `read_image`'s area downscale): its edges alias, and it is scored against a smoother photo."""
    return int(min(max(round(focal / view.intrinsics[0]), 1), MAX_RAYS_A_SIDE))


def supersampling_note(views: list[View], focal: float) -> str | None:
    """What `evaluate(focal=...)` does to these views, in a sentence (None when every view gets one ray a pixel)."""
    coarse = [(v, k) for v in views if (k := rays_a_side(v, focal)) > 1]
    if not coarse:
        return None
    ks = sorted({k for _, k in coarse})
    view = coarse[0][0]
    return (f"{len(coarse)} of {len(views)} views are coarser than the training photos (e.g. {view.name}: "
            f"{view.hw[1]}×{view.hw[0]} px, focal {view.intrinsics[0]:.0f} px against the photos' {focal:.0f}): each of "
            f"their pixels is the mean of {' or '.join(f'{k}×{k}' for k in ks)} rays, as a downscaled photo's pixel is "
            "the mean of its area")


EXPOSURE_COST_DB = 1.0
"""What fitting each held-out photo's colours must gain over the same pixels unfitted before `fitted_note` says the
photos' exposure changes cost the plain score: a field of photos at one exposure gains little from the fit (which
also absorbs its own small colour bias), where the fox's changing exposure, unmodelled, scores 23.91 dB whole and
29.55 dB fitted (benchmarks/results/fox_fast_exposure.json)."""


def fitted_note(result: dict[str, Any]) -> str | None:
    """`evaluate`'s ``psnr_fitted`` against ``psnr_right_half`` (the same pixels unfitted), in a sentence that draws
    only the conclusion the gap supports (None where the result has no fitted score)."""
    if "psnr_fitted" not in result or "psnr_right_half" not in result:
        return None
    gain = result["psnr_fitted"] - result["psnr_right_half"]
    said = (f"test views with each photo's colours fitted on its left half, its right half scored (as a field with "
            f"per-photo appearance is scored): PSNR {result['psnr_fitted']:.2f} dB against {result['psnr_right_half']:.2f}"
            f" dB for the same halves unfitted")
    if gain >= EXPOSURE_COST_DB:
        return (f"{said}: the photos' exposure or colour balance changes cost the plain score {gain:.1f} dB "
                "(train.appearance=on models them)")
    return f"{said}: the photos' exposure changes cost the plain score little"


def render_view(model: torch.nn.Module, view: View, aabb: torch.Tensor | None, background: np.ndarray, chunk: int | None = None,
                autocast: torch.dtype | None = None, colors: bool = True, rays_side: int = 1) -> dict[str, np.ndarray]:
    """Render a view at its resolution → numpy rgb (H, W, 3), depth (H, W), opacity (H, W); ``colors=False``: depth
    and opacity only (`recon.nerf.evaluate.render_image`). ``rays_side`` k > 1: each pixel is the mean of k×k rays
    spread evenly over it (`rays_a_side`)."""
    from recon.nerf.evaluate import render_image

    h, w = view.hw
    k = max(1, int(rays_side))
    device = next(model.parameters()).device
    kwargs: dict[str, Any] = {"aabb": aabb} if aabb is not None else {"near": view.near, "far": view.far}
    # pixel centres sit at i + 0.5 (recon.nerf.rays): scaling the intrinsics by k puts k×k sub-pixel centres in each pixel
    out = render_image(model, torch.tensor(view.c2w, dtype=torch.float32, device=device),
                       tuple(float(x) * k for x in view.intrinsics), h * k, w * k, chunk,
                       background=torch.tensor(background), autocast=autocast, colors=colors, **kwargs)
    if k > 1:
        out = {name: v.reshape(h, k, w, k, *v.shape[2:]).mean(dim=(1, 3)) for name, v in out.items()}
    return {name: v.detach().cpu().numpy() for name, v in out.items()}


def view_tensors(views: list[View], device: torch.device) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor]:
    """The views as tensors on `device`: images, camera-to-world (N, 4, 4), intrinsics (N, 4), near/far (N, 2)."""
    images = [torch.from_numpy(v.image).to(device) for v in views]
    c2w = torch.tensor(np.stack([v.c2w for v in views]), dtype=torch.float32, device=device)
    intr = torch.tensor([v.intrinsics for v in views], dtype=torch.float32, device=device)
    near_far = torch.tensor([[v.near, v.far] for v in views], dtype=torch.float32, device=device)
    return images, c2w, intr, near_far


def target_rgb(view: View, background: np.ndarray) -> np.ndarray:
    img = view.image.astype(np.float32) / 255.0
    if img.shape[-1] == 4:
        return img[..., :3] * img[..., 3:] + background * (1 - img[..., 3:])
    return img


def evaluate(model: torch.nn.Module, views: list[View], aabb: torch.Tensor | None, background: np.ndarray, keep: bool = False,
             autocast: torch.dtype | None = None, appearance: bool = False, align_poses: bool = False,
             focal: float | None = None, fitted: bool = True,
             on_view: Callable[[], None] | None = None) -> dict[str, Any]:
    """PSNR/SSIM of renders against photos; with keep=True also the renders themselves. ``on_view`` is called after
    each view (a progress bar's advance: 200 views at 2×2 rays a pixel take minutes on a CPU).

    focal: the training photos' focal length in pixels (`training_focal`); a view coarser than them is rendered
    with k×k rays a pixel (`rays_a_side`, kept as the view's ``rays_a_side``), as its photo averages each pixel's area.

    appearance=True (a field trained with per-photo appearance): each photo's colour transform is fitted on
    its left half and the right half is scored (recon.nerf.evaluate.HELD_OUT_PROTOCOL); the full-image
    PSNR of the neutral render is kept as ``psnr_neutral``. align_poses=True (a field trained with refined poses):
    each photo's pose is first fitted on its left half (recon.nerf.evaluate.POSE_PROTOCOL); the right half is
    scored, and the PSNR at the given pose over the whole photo is kept as ``psnr_given_pose``. A field without
    either is also scored as an appearance field is, ``psnr_fitted``: its PSNR then says how much of a lower score
    is the photos' changing exposure, and compares with a run that modelled it; ``psnr_right_half`` scores the same
    right halves without the fit, so the two differ by what the fit gains alone (the halves' content differs from the
    whole photo's by more than a constant exposure does). fitted=False skips both, for the evaluations during
    training, which read the PSNR and SSIM alone.
    """
    from dataclasses import replace

    from recon.evaluation.metrics import psnr, ssim
    from recon.nerf.evaluate import align_pose, held_out_right_half, left_right_split

    per_view, renders = [], []
    for view in views:
        k = rays_a_side(view, focal) if focal else 1
        extra: dict[str, Any] = {"rays_a_side": k} if k > 1 else {}
        gt = target_rgb(view, background)
        if align_poses:
            given = render_view(model, view, aabb, background, autocast=autocast, rays_side=k)
            extra["psnr_given_pose"] = round(float(psnr(torch.from_numpy(given["rgb"]), torch.from_numpy(gt))), 3)
            device = next(model.parameters()).device
            left, _ = left_right_split(view.hw[1])
            kwargs: dict[str, Any] = {"aabb": aabb} if aabb is not None else {"near_far": (view.near, view.far)}
            c2w = align_pose(model, torch.from_numpy(np.ascontiguousarray(gt[:, left])),
                             torch.tensor(view.c2w, dtype=torch.float32, device=device), view.intrinsics,
                             background=torch.tensor(background, dtype=torch.float32), **kwargs)
            view = replace(view, c2w=c2w.cpu().double().numpy())
        out = render_view(model, view, aabb, background, autocast=autocast, rays_side=k)
        pred, ref = out["rgb"], gt
        alpha = view.image.shape[-1] == 4  # only the field's part of a photo with alpha goes through the transform
        if appearance:
            extra["psnr_neutral"] = round(float(psnr(torch.from_numpy(pred), torch.from_numpy(gt))), 3)
            pred, ref = held_out_right_half(pred, gt, out["opacity"] if alpha else None, background if alpha else None)
        elif align_poses:
            _, right = left_right_split(view.hw[1])
            pred, ref = np.ascontiguousarray(pred[:, right]), np.ascontiguousarray(gt[:, right])
        elif fitted:
            halves = held_out_right_half(pred, gt, out["opacity"] if alpha else None, background if alpha else None)
            extra["psnr_fitted"] = round(float(psnr(*(torch.from_numpy(x) for x in halves))), 3)
            _, right = left_right_split(view.hw[1])
            extra["psnr_right_half"] = round(float(psnr(torch.from_numpy(np.ascontiguousarray(pred[:, right])),
                                                        torch.from_numpy(np.ascontiguousarray(gt[:, right])))), 3)
        p = float(psnr(torch.from_numpy(pred), torch.from_numpy(ref)))
        s = float(ssim(torch.from_numpy(pred), torch.from_numpy(ref)))
        per_view.append({"view": view.name, "psnr": round(p, 3), "ssim": round(s, 4), **extra})
        if keep:
            renders.append((view, out, gt))
        if on_view is not None:
            on_view()
    result: dict[str, Any] = {
        "psnr": float(np.mean([v["psnr"] for v in per_view])) if per_view else math.nan,
        "ssim": float(np.mean([v["ssim"] for v in per_view])) if per_view else math.nan,
        "views": per_view,
    }
    if appearance and per_view:
        result["psnr_neutral"] = float(np.mean([v["psnr_neutral"] for v in per_view]))
    if fitted and not (appearance or align_poses) and per_view:
        result["psnr_fitted"] = float(np.mean([v["psnr_fitted"] for v in per_view]))
        result["psnr_right_half"] = float(np.mean([v["psnr_right_half"] for v in per_view]))
    if align_poses and per_view:
        result["psnr_given_pose"] = float(np.mean([v["psnr_given_pose"] for v in per_view]))
    if keep:
        result["renders"] = renders
    return result


def write_previews(renders: list, folder: Path, near: float | None = None, far: float | None = None) -> None:
    """One PNG per rendered view, `folder/NAME.png`: photo | render | colored depth (renders from `evaluate(keep=True)`)."""
    from recon.nerf.device import cpu_threads
    from recon.plots import comparison_panel, depth_to_color

    folder.mkdir(parents=True, exist_ok=True)

    def write(render: tuple) -> None:
        view, out, gt = render
        comparison_panel(out["rgb"], gt, depth_to_color(out["depth"], out["opacity"], near, far), folder / f"{view.name}.png")

    # on every core: PNG compression lets go of the GIL, and a full evaluation writes one panel per test view
    with ThreadPoolExecutor(max_workers=max(1, min(len(renders), cpu_threads()))) as pool:
        list(pool.map(write, renders))
