"""A pure training loop for any :class:`~recon.nerf.render.RadianceModel` (no files, no configs).

Pieces:

* :class:`RayBatcher` holds every training pixel (colors + which camera/pixel) and yields
  shuffled batches mixed across images, with rays computed on the fly (cheap) so that memory is
  that of the images, not of the rays. Shuffling uses its own seeded generators: same seed, same
  batches.
* :func:`train` runs Adam + MSE with an exponential learning-rate decay, calls callbacks after
  every step (checkpointing, evaluation, logging are the caller's business), and stops with
  :class:`TrainingDiverged` on a non-finite loss. A run resumed from :meth:`TrainProgress.state_dict`
  continues exactly as the uninterrupted run would (same batches, same jitter, same updates).
* :func:`render_image` renders a full camera in chunks under ``no_grad``.

Camera conventions: see :mod:`recon.nerf.rays` (OpenGL c2w, pixel centres, pinhole, unit rays_d).
"""
from __future__ import annotations

import copy
import itertools
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ..metrics import mse_to_psnr
from .rays import camera_rays, pixel_rays, ray_aabb
from .pose_refine import PoseRefinement
from .render import RadianceModel

__all__ = [
    "RayBatcher",
    "TrainProgress",
    "TrainingDiverged",
    "TrainingInterrupted",
    "align_pose",
    "lr_at",
    "make_optimizer",
    "render_image",
    "train",
]


# ----------------------------------------------------------------------------- errors
class TrainingDiverged(RuntimeError):
    """The loss became NaN or infinite. Carries the step, the cause and what to try."""

    def __init__(self, step: int, cause: str, advice: str) -> None:
        self.step, self.cause, self.advice = step, cause, advice
        super().__init__(f"training diverged at step {step}: {cause}. {advice}")


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`; ``.state`` is a resumable state after ``.step`` finished steps."""

    def __init__(self, step: int, state: dict[str, Any]) -> None:
        self.step, self.state = step, state
        super().__init__(f"training interrupted after step {step}")


# ----------------------------------------------------------------------------- data
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
        empty: per image an (H, W) bool mask (tensor or array) of pixels known to see nothing up to
            ``far`` (the sky, `recon.sky`); each batch then carries ``empty (B,)`` (float 0/1) for the
            trainer's ``empty_weight``.
        drop_missed: with ``aabb``, leave out pixels whose rays miss the box (they can only show
            background); the count is in ``n_dropped``.
        seed: seeds the shuffling and random-background generators.
        device: where batches are produced (default: the images' device).

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
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long, device=self.device), torch.cumsum(sizes[:, 0] * sizes[:, 1], 0)])
        self.c2w = c2w[:, :3, :4].to(self.device, torch.float32)
        self.intrinsics = intrinsics.to(self.device, torch.float32)
        self.aabb = None if aabb is None else aabb.to(self.device, torch.float32)
        if near_far is not None:
            nf = near_far.to(self.device, torch.float32)
            self.near_far = nf.expand(n, 2) if nf.shape == (2,) else nf
            if self.near_far.shape != (n, 2):
                raise ValueError(f"near_far must be (2,) or ({n}, 2), got {tuple(near_far.shape)}")
        else:
            self.near_far = None
        self.empty: Tensor | None = None
        if empty is not None:
            if len(empty) != n or any(tuple(m.shape) != tuple(im.shape[:2]) for m, im in zip(empty, imgs, strict=True)):
                raise ValueError("empty must hold one (H, W) mask per image, each the size of its image")
            self.empty = torch.cat([torch.as_tensor(m, dtype=torch.bool).reshape(-1) for m in empty]).to(self.device)
        self.background = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        self.random_background = random_background and self.has_alpha
        self.seed = seed
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
        self._perm_gen = torch.Generator().manual_seed(seed)
        self._bg_gen = torch.Generator(device=self.device).manual_seed(seed + 1)
        self._new_epoch()

    # -- pixel bookkeeping
    def image_index(self, flat: Tensor) -> Tensor:
        """Flat pixel indices (B,) -> the index (B,) long of the image each pixel belongs to."""
        return torch.searchsorted(self.offsets, flat, right=True) - 1

    def _rays(self, flat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Flat pixel indices (B,) -> rays_o, rays_d (B, 3), near, far (B,), hit (B,) bool."""
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
        return o, d, near, far, hit

    def _new_epoch(self) -> None:
        self._epoch_gen_state = self._perm_gen.get_state()
        self._perm = torch.randperm(self.n_rays, generator=self._perm_gen)
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
        idx = torch.cat(parts).to(self.device)
        return idx if self.valid is None else self.valid[idx]

    def next_batch(self, batch_rays: int) -> dict[str, Tensor]:
        """The next ``batch_rays`` rays of the shuffled epoch (crossing into the next epoch as needed)."""
        flat = self._take(batch_rays)
        o, d, near, far, _ = self._rays(flat)
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
                 "image": self.image_index(flat)}
        if self.empty is not None:
            batch["empty"] = self.empty[flat].float()
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


# ----------------------------------------------------------------------------- optimization
def make_optimizer(model: RadianceModel, lr: float) -> torch.optim.Adam:
    """Adam over ``model.param_groups(lr)``; fused kernel when the device/dtypes allow it.

    Fused Adam is ~20x faster on large grids on the CPU (CPU_NERF_NOTES.md, lesson 1). Each group
    remembers its starting rate as ``initial_lr`` for the decay schedule.
    """
    groups = model.param_groups(lr)
    for g in groups:
        g.setdefault("initial_lr", g.get("lr", lr))
    try:
        return torch.optim.Adam(groups, lr=lr, fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.Adam(groups, lr=lr)


def lr_at(step: int, steps: int, lr: float, lr_final: float | None, fraction: float | None = None) -> float:
    """Exponential decay from ``lr`` at step 0 to ``lr_final`` at ``steps`` (constant if lr_final is None).

    ``fraction`` (of the training done, e.g. of a time budget) overrides ``step / steps`` when larger.
    """
    if lr_final is None or steps <= 0:
        return lr
    frac = min(step, steps) / steps
    if fraction is not None:
        frac = min(max(frac, fraction), 1.0)
    return lr * (lr_final / lr) ** frac


def _rng_state() -> dict[str, Any]:
    state: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


@dataclass
class TrainProgress:
    """What callbacks see after each step.

    ``state_dict()`` builds (on demand: it copies the model) a resumable training state: pass it
    as ``train(..., state=...)`` with a fresh model/batcher built the same way to continue.
    """

    step: int
    steps: int
    loss: float
    psnr: float
    lr: float
    elapsed_s: float
    rays_per_s: float
    metrics: dict[str, float] | None = None
    state_fn: Callable[[], dict[str, Any]] = field(default=lambda: {}, repr=False)

    def state_dict(self) -> dict[str, Any]:
        return self.state_fn()


class StallDetector:
    """Warns once when the batch PSNR has not risen after the first stretch of training.

    A learning rate far too high can collapse a model to one flat color (no NaN, a loss that never
    falls); far too low, nothing moves. Both are silent failures unless someone looks; this names them.
    Compares the mean PSNR of steps 1–5 with that of the 5 steps before ``check_at``.
    """

    MIN_GAIN_DB = 0.5

    def __init__(self, steps: int) -> None:
        self.check_at = min(max(20, steps // 20), steps) if steps >= 20 else 0
        self.first: list[float] = []
        self.recent: list[float] = []

    def observe(self, step: int, psnr: float, lr: float) -> None:
        if not self.check_at or step > self.check_at:
            return
        if step <= 5:
            self.first.append(psnr)
        if step > self.check_at - 5:
            self.recent.append(psnr)
        if step == self.check_at:
            start, now = sum(self.first) / len(self.first), sum(self.recent) / len(self.recent)
            if now < start + self.MIN_GAIN_DB:
                warnings.warn(
                    f"training is not improving: batch PSNR {start:.2f} dB at the start, {now:.2f} dB after {step} "
                    f"steps. The learning rate ({lr:.3g}) may be far too high (the model collapses to a flat color) "
                    f"or far too low; try a value 10x lower or higher (--set train.lr=...).",
                    UserWarning,
                    stacklevel=3,
                )


def _diagnose(out: dict[str, Any], loss_terms: dict[str, Tensor]) -> str:
    bad = [name for name, v in loss_terms.items() if not torch.isfinite(v).all()]
    rgb_bad = not torch.isfinite(out["rgb"]).all()
    cause = "loss is " + ("NaN" if any(torch.isnan(v).any() for v in loss_terms.values()) else "infinite")
    cause += f" (non-finite terms: {', '.join(bad)}"
    cause += "; rendered colors contain NaN/inf)" if rgb_bad else ")"
    return cause


def train(
    model: RadianceModel,
    batcher: RayBatcher,
    *,
    steps: int,
    lr: float,
    lr_final: float | None = None,
    batch_rays: int = 4096,
    eval_fn: Callable[[RadianceModel, int], dict[str, float]] | None = None,
    eval_every: int = 0,
    callbacks: Iterable[Callable[[TrainProgress], None]] = (),
    state: dict[str, Any] | None = None,
    history_every: int = 100,
    autocast: torch.dtype | None = None,
    budget_s: float = 0.0,
    spent_s: float = 0.0,
    extra_loss: Callable[[RadianceModel, int], dict[str, Tensor]] | None = None,
    appearance: torch.nn.Module | None = None,
    pose_refine: PoseRefinement | None = None,
    empty_weight: float = 0.0,
) -> dict[str, Any]:
    """Optimize ``model`` on ``batcher``'s rays for ``steps`` steps (or the rest of them after a resume).

    Loss: MSE of the rendered rgb against the targets, plus the MSE of every ``aux_rgb``
    prediction (e.g. the coarse network) and the model's already-weighted ``reg`` term.
    PSNR is reported from the main rgb MSE. The learning rate decays exponentially from ``lr``
    to ``lr_final`` (per group, relative to each group's own starting rate).

    Each step calls ``model.step_update(step)`` first, then renders with ``training=True``.
    ``eval_fn(model, step)`` runs every ``eval_every`` steps (and after the last step) under
    ``no_grad`` in eval mode; its metrics reach the callbacks. Callbacks run after every step.

    Args:
        state: a dict from :meth:`TrainProgress.state_dict` to resume from; model and batcher
            must be constructed as for the original run.
        history_every: record (step, loss, psnr) every this many steps in the result.
        budget_s: > 0: stop once this much training time (evaluation excluded; ``spent_s`` of it
            already used before a resume) is spent; the learning rate then decays with the
            fraction of the budget used, so a budget-bound run still ends at ``lr_final``.
        autocast: e.g. ``torch.bfloat16`` to run the model's matmuls in mixed precision
            (``torch.autocast``); ~2x faster MLPs on CPUs with AMX/AVX512-BF16. Losses, and volume
            rendering in models that cast their network outputs to float32, stay in float32.
        extra_loss: ``(model, step) -> {name: loss}`` terms added to the loss each step (e.g. the sparse-depth
            prior of :mod:`recon.nerf.depth_prior`); it renders its own rays. Must be deterministic in the step
            for resumes to repeat the run.
        appearance: per-photo colour transforms (:class:`recon.nerf.appearance.PhotoAppearance`):
            ``appearance(out, batch["image"])`` replaces the rendered rgb before the loss, its
            ``regularizer()`` joins the loss and its parameters are optimized at ``lr``.
        pose_refine: per-photo camera corrections (:class:`recon.nerf.pose_refine.PoseRefinement`): each batch's
            rays are cast from the corrected cameras, its ``regularizer()`` joins the loss and its parameters are
            optimized by their own Adam at ``pose_refine.lr`` on the steps ``pose_refine.learns_at``, each update
            followed by ``pose_refine.hold_frame()``.
        empty_weight: with a batcher given ``empty`` masks (ignored without them): adds ``empty_weight`` × the
            mean over the batch of the sky rays' opacity (L1: a blob coloured like the sky costs the colour loss
            almost nothing).

    Returns a summary dict: step, loss, psnr, rays_per_s, elapsed_s, history, metrics (last eval).

    Raises:
        TrainingDiverged: on a NaN/inf loss, naming the step and suggesting a lower rate.
        TrainingInterrupted: on Ctrl-C, carrying a resumable state of the finished steps.
    """
    opt = make_optimizer(model, lr)
    if appearance is not None:
        opt.add_param_group({"params": list(appearance.parameters()), "lr": lr, "initial_lr": lr})
    if pose_refine is not None:
        # its own Adam at a fixed small rate: the field's rate schedule would turn cameras 1,000x too fast
        pose_opt = torch.optim.Adam(pose_refine.parameters(), lr=pose_refine.lr)
    start = 0
    if state is not None:
        model.load_state_dict(state["model"])
        if appearance is not None:
            appearance.load_state_dict(state["appearance"])
        if pose_refine is not None:
            pose_refine.load_state_dict(state["pose_refine"])
            pose_opt.load_state_dict(state["pose_optimizer"])
        opt.load_state_dict(state["optimizer"])
        batcher.load_state_dict(state["batcher"])
        _set_rng_state(state["rng"])
        start = int(state["step"])
    done = start

    def snapshot() -> dict[str, Any]:
        return {
            "step": done,
            "model": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "optimizer": copy.deepcopy(opt.state_dict()),
            "batcher": batcher.state_dict(),
            "rng": _rng_state(),
            **({"appearance": {k: v.detach().clone() for k, v in appearance.state_dict().items()}} if appearance is not None else {}),
            **({"pose_refine": {k: v.detach().clone() for k, v in pose_refine.state_dict().items()},
                "pose_optimizer": copy.deepcopy(pose_opt.state_dict())} if pose_refine is not None else {}),
        }

    history: list[tuple[int, float, float]] = []
    metrics: dict[str, float] | None = None
    loss_v = psnr_v = math.nan
    callbacks = list(callbacks)
    t0 = time.perf_counter()
    eval_s = 0.0
    stall = StallDetector(steps) if start == 0 else StallDetector(0)
    try:
        for step in range(start, steps):
            fraction = None
            if budget_s > 0:
                used = spent_s + time.perf_counter() - t0 - eval_s
                if used >= budget_s:
                    break
                fraction = used / budget_s
            cur_lr = lr_at(step, steps, lr, lr_final, fraction)
            for g in opt.param_groups:
                g["lr"] = g["initial_lr"] * cur_lr / lr
            model.train()
            if model.step_update(step):
                opt.state.clear()  # grids were re-sampled: old Adam moments point at other places
            batch = batcher.next_batch(batch_rays)
            refine_poses = pose_refine is not None and pose_refine.learns_at(step, steps, fraction)
            if pose_refine is not None:
                with torch.set_grad_enabled(refine_poses):
                    batch = pose_refine.correct_batch(batch, batcher.aabb)
            with torch.autocast(batch["rgb"].device.type, dtype=autocast or torch.bfloat16, enabled=autocast is not None):
                out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"],
                                        training=True, background=batch["background"])
            if appearance is not None:
                out = {**out, "rgb": appearance(out, batch["image"])}
            terms = {"rgb": F.mse_loss(out["rgb"].float(), batch["rgb"])}
            for i, aux in enumerate(out.get("aux_rgb", [])):
                terms[f"aux_rgb[{i}]"] = F.mse_loss(aux.float(), batch["rgb"])
            if "reg" in out:
                terms["reg"] = out["reg"].float()
            if empty_weight > 0 and "empty" in batch:  # sky pixels: whatever the field holds on their rays is wrong
                terms["empty"] = empty_weight * (out["opacity"].float() * batch["empty"]).mean()
            if extra_loss is not None:
                with torch.autocast(batch["rgb"].device.type, dtype=autocast or torch.bfloat16, enabled=autocast is not None):
                    terms.update({k: v.float() for k, v in extra_loss(model, step).items()})
            if appearance is not None:
                terms["appearance"] = appearance.regularizer()
            if refine_poses:
                terms["pose"] = pose_refine.regularizer()
            loss = sum(terms.values())
            loss_v = float(loss.detach())
            if not math.isfinite(loss_v):
                raise TrainingDiverged(
                    step, _diagnose(out, terms),
                    f"Lower the learning rate (now {cur_lr:.3g}; try {cur_lr / 3:.3g}) and resume from the "
                    "last checkpoint taken before this step; if it recurs at the same step, check the "
                    "input images and poses for NaN or extreme values.",
                )
            opt.zero_grad(set_to_none=True)
            if refine_poses:
                pose_opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if refine_poses:
                pose_opt.step()
                pose_refine.hold_frame()
            done = step + 1
            psnr_v = float(mse_to_psnr(terms["rgb"].detach()))
            stall.observe(done, psnr_v, cur_lr)
            if history_every and done % history_every == 0:
                history.append((done, loss_v, psnr_v))
            if eval_fn is not None and eval_every and (done % eval_every == 0 or done == steps):
                model.eval()
                t_eval = time.perf_counter()
                with torch.no_grad():
                    metrics = eval_fn(model, done)
                eval_s += time.perf_counter() - t_eval
                model.train()
            elapsed = time.perf_counter() - t0
            progress = TrainProgress(
                step=done, steps=steps, loss=loss_v, psnr=psnr_v, lr=cur_lr, elapsed_s=elapsed,
                rays_per_s=(done - start) * batch_rays / max(elapsed, 1e-9),
                metrics=metrics if (eval_every and done % eval_every == 0) or done == steps else None,
                state_fn=snapshot,
            )
            for cb in callbacks:
                cb(progress)
    except KeyboardInterrupt as e:
        raise TrainingInterrupted(done, snapshot()) from e
    elapsed = time.perf_counter() - t0
    return {"step": done, "loss": loss_v, "psnr": psnr_v, "elapsed_s": elapsed,
            "rays_per_s": (done - start) * batch_rays / max(elapsed, 1e-9), "history": history, "metrics": metrics}


# ----------------------------------------------------------------------------- inference
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
) -> dict[str, Tensor]:
    """Render one camera, ``chunk`` rays at a time (default: the model's ``render_chunk``, else 8192), under
    ``inference_mode`` in eval mode.

    Args:
        c2w: (4, 4) or (3, 4) camera-to-world (OpenGL); intrinsics: fl_x, fl_y, cx, cy (pixels).
        aabb: (2, 3) scene box giving near/far per ray (rays missing it show the background
            without running the model); or give ``near`` and ``far`` distances.
        autocast: mixed-precision dtype for the model (see :func:`train`), or None.

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
    chunk = chunk or int(getattr(model, "render_chunk", 8192))
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode(), torch.autocast(device.type, dtype=autocast or torch.bfloat16, enabled=autocast is not None):
            for s in range(0, idx.numel(), chunk):
                i = idx[s : s + chunk]
                out = model.render_rays(o[i], d[i], t0[i], t1[i], training=False, background=bg)
                rgb[i], depth[i], opacity[i] = out["rgb"].float(), out["depth"].float(), out["opacity"].float()
    finally:
        model.train(was_training)
    return {"rgb": rgb.view(h, w, 3), "depth": depth.view(h, w), "opacity": opacity.view(h, w)}


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
