"""A pure training loop for any :class:`~recon.nerf.render.RadianceModel` (no files, no configs).

Pieces:

* :func:`train` runs Adam + MSE with an exponential learning-rate decay, calls callbacks after
  every step (checkpointing, evaluation, logging are the caller's business), and stops with
  :class:`TrainingDiverged` on a non-finite loss. A run resumed from :meth:`TrainProgress.state_dict`
  continues exactly as the uninterrupted run would (same batches, same jitter, same updates).

Its rays come from a :class:`recon.nerf.fitting.RayBatcher`. Reading a trained field (rendering a camera, scoring
held-out photos) is :mod:`recon.nerf.evaluate`'s: nothing that only uses a field imports this module.
"""
from __future__ import annotations

import copy
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import torch
import torch.nn.functional as F
from torch import Tensor

from ..metrics import mse_to_psnr
from .fitting import RayBatcher, lr_at
from .pose_refine import PoseRefinement
from .render import RadianceModel

__all__ = [
    "TrainProgress",
    "TrainingDiverged",
    "TrainingInterrupted",
    "make_optimizer",
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
            # one host read for both numbers, before backward: on CUDA a read after opt.step() would wait for the
            # whole step and leave the GPU idle while the next batch is prepared
            loss_v, rgb_mse = torch.stack([loss.detach().float(), terms["rgb"].detach()]).tolist()
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
            psnr_v = float(mse_to_psnr(torch.tensor(rgb_mse, dtype=torch.float32)))  # as from the float32 loss
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
