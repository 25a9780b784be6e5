"""A pure training loop for any :class:`~recon.nerf.render.RadianceModel` (no files, no configs).

* :class:`TrainStep` is one step: Adam on the colour MSE plus the model's regularizer and the terms of the step's
  pieces (:mod:`recon.nerf.pieces`: sky rays, the depth prior, per-photo appearance, pose refinement), with an
  exponential learning-rate decay.
* :func:`train` loops over it, calls callbacks after every step (checkpointing, evaluation, logging are the
  caller's business), and stops with :class:`TrainingDiverged` on a non-finite loss. A run resumed from
  :meth:`TrainProgress.state_dict` continues exactly as the uninterrupted run would (same batches, same jitter,
  same updates).

Its rays come from a :class:`recon.nerf.fitting.RayBatcher`. Reading a trained field (rendering a camera, scoring
held-out photos) is :mod:`recon.nerf.evaluate`'s: nothing that only uses a field imports this module.
"""
from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from recon.evaluation.metrics import mse_to_psnr

from .fitting import RayBatcher, lr_at, training_done
from .masked_adam import MaskedAdam
from .pieces import StepInfo, TrainPiece, mixed_precision
from .render import RadianceModel

__all__ = [
    "StepResult",
    "TrainProgress",
    "TrainStep",
    "TrainingDiverged",
    "TrainingInterrupted",
    "make_optimizer",
    "train",
    "warm_up",
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
def make_optimizer(model: RadianceModel, lr: float, optimizer: str = "adam",
                   beta2: float = 0.999) -> torch.optim.Optimizer:
    """The optimizer over ``model.param_groups(lr)``: "adam" torch's Adam, fused where the device and dtypes allow
    (~20x faster on large grids on the CPU: CPU_NERF_NOTES.md, lesson 1); "masked_adam"
    :class:`recon.nerf.masked_adam.MaskedAdam`, which updates only the grid values a step's rays touched (groups
    marked ``masked``). Each group remembers its starting rate as ``initial_lr`` for the decay schedule; ``beta2``:
    Adam's second beta (the first stays 0.9)."""
    groups = model.param_groups(lr)
    for g in groups:
        g.setdefault("initial_lr", g.get("lr", lr))
    if optimizer == "masked_adam":
        return MaskedAdam(groups, lr=lr, betas=(0.9, beta2))
    if optimizer != "adam":
        raise ValueError(f"optimizer must be 'adam' or 'masked_adam', got {optimizer!r}")
    try:
        return torch.optim.Adam(groups, lr=lr, betas=(0.9, beta2), fused=True)
    except (RuntimeError, ValueError):
        return torch.optim.Adam(groups, lr=lr, betas=(0.9, beta2))


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


@dataclass
class StepResult:
    """One step's loss, its colour MSE (PSNR is reported from it), the learning rate and the rendered output."""

    loss: float
    rgb_mse: float
    lr: float
    out: dict[str, Any]


class TrainStep:
    """One optimization step of :func:`train`, callable step by step: the rate schedule, a batch, the pieces'
    hooks, the render under autocast, the loss and the updates.

    :func:`train` loops over it; a benchmark that times single steps calls it directly, so what it times is the
    step the train stage runs. Loss: MSE of the rendered rgb against the targets, plus the MSE of every ``aux_rgb``
    prediction (e.g. the coarse network), the model's already-weighted ``reg`` term, then each piece's terms in the
    pieces' order (:mod:`recon.nerf.pieces`). The learning rate decays exponentially from ``lr`` to ``lr_final``
    (per group, relative to each group's own starting rate). Each step calls ``model.step_update(step)`` first, then
    renders with ``training=True``.

    Args:
        autocast: e.g. ``torch.bfloat16`` to run the model's matmuls in mixed precision (``torch.autocast``);
            ~2x faster MLPs on CPUs with AMX/AVX512-BF16. Losses, and volume rendering in models that cast their
            network outputs to float32, stay in float32.
        optimizer: "adam" or "masked_adam" (:func:`make_optimizer`); beta2: its second beta.
    """

    def __init__(self, model: RadianceModel, batcher: RayBatcher, *, steps: int, lr: float,
                 lr_final: float | None = None, batch_rays: int = 4096, pieces: Sequence[TrainPiece] = (),
                 autocast: torch.dtype | None = None, optimizer: str = "adam", beta2: float = 0.999) -> None:
        self.model, self.batcher, self.steps, self.lr, self.lr_final = model, batcher, steps, lr, lr_final
        self.batch_rays, self.pieces, self.autocast = batch_rays, list(pieces), autocast
        self.opt = make_optimizer(model, lr, optimizer, beta2)
        for piece in self.pieces:
            piece.attach(self.opt, lr)

    def __call__(self, step: int, fraction: float | None = None) -> StepResult:
        """Take step ``step`` (from 0); ``fraction``: the share of a time budget spent, which then sets the rate.

        Raises TrainingDiverged on a NaN/inf loss, before anything is updated."""
        model, opt = self.model, self.opt
        cur_lr = lr_at(step, self.steps, self.lr, self.lr_final, fraction)
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * cur_lr / self.lr
        model.train()
        model.set_progress(training_done(step, self.steps, fraction))
        if model.step_update(step):
            opt.state.clear()  # grids were re-sampled: old Adam moments point at other places
        at = StepInfo(step, self.steps, fraction, self.autocast)
        batch = self.batcher.next_batch(self.batch_rays)
        for piece in self.pieces:
            batch = piece.before_render(batch, at)
        with mixed_precision(batch["rgb"].device.type, self.autocast):
            out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"],
                                    training=True, background=batch["background"])
        for piece in self.pieces:
            out = piece.after_render(out, batch)
        terms = {"rgb": F.mse_loss(out["rgb"].float(), batch["rgb"])}
        for i, aux in enumerate(out.get("aux_rgb", [])):
            terms[f"aux_rgb[{i}]"] = F.mse_loss(aux.float(), batch["rgb"])
        if "reg" in out:
            terms["reg"] = out["reg"].float()
        for piece in self.pieces:
            terms.update(piece.loss_terms(model, out, batch, at))
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
        loss.backward()
        opt.step()
        for piece in self.pieces:
            piece.after_step(at)
        return StepResult(loss_v, rgb_mse, cur_lr, out)

    def state_dict(self, weights: bool = True) -> dict[str, Any]:
        """Model, optimizer, batcher position, RNG and the pieces' own entries (copies: training goes on).
        weights=False: all but the model and the optimizer's moments, for a finished field saved on its own."""
        state: dict[str, Any] = {"batcher": self.batcher.state_dict(), "rng": _rng_state()}
        if weights:
            state["model"] = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
            state["optimizer"] = copy.deepcopy(self.opt.state_dict())
        for piece in self.pieces:
            state.update(piece.state_dict())
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """A state without "optimizer" (a finished field trained on) starts the optimizer's moments again."""
        self.model.load_state_dict(state["model"])
        for piece in self.pieces:
            piece.load_state_dict(state)
        if "optimizer" in state:
            self.opt.load_state_dict(state["optimizer"])
        self.batcher.load_state_dict(state["batcher"])
        _set_rng_state(state["rng"])


def warm_up(model: RadianceModel, batcher: RayBatcher, batch_rays: int = 4096,
            autocast: torch.dtype | None = None) -> float:
    """One training render of a batch and its backward, then everything as it was (no parameter moved, no gradient
    kept, the batcher's stream and the random state restored): on CUDA the kernels (Triton's, the compiled graphs')
    compile here, before a time budget starts, instead of in its first steps. Returns the seconds it took."""
    t0 = time.perf_counter()
    stream, rng = batcher.state_dict(), _rng_state()
    was_training = model.training
    model.train()
    batch = batcher.next_batch(min(batch_rays, batcher.n_rays))
    with mixed_precision(batch["rgb"].device.type, autocast):
        out = model.render_rays(batch["rays_o"], batch["rays_d"], batch["near"], batch["far"], training=True,
                                background=batch["background"])
    loss = F.mse_loss(out["rgb"].float(), batch["rgb"]) + (out["reg"].float() if "reg" in out else 0.0)
    loss.backward()
    model.zero_grad(set_to_none=True)
    model.train(was_training)
    batcher.load_state_dict(stream)
    _set_rng_state(rng)
    if batch["rgb"].device.type == "cuda":
        torch.cuda.synchronize(batch["rgb"].device)
    return time.perf_counter() - t0


def train(
    model: RadianceModel,
    batcher: RayBatcher,
    *,
    steps: int,
    lr: float,
    lr_final: float | None = None,
    batch_rays: int = 4096,
    pieces: Sequence[TrainPiece] = (),
    eval_fn: Callable[[RadianceModel, int], dict[str, float]] | None = None,
    eval_every: int = 0,
    callbacks: Iterable[Callable[[TrainProgress], None]] = (),
    state: dict[str, Any] | None = None,
    history_every: int = 100,
    autocast: torch.dtype | None = None,
    budget_s: float = 0.0,
    spent_s: float = 0.0,
    optimizer: str = "adam",
    beta2: float = 0.999,
) -> dict[str, Any]:
    """Optimize ``model`` on ``batcher``'s rays for ``steps`` steps (or the rest of them after a resume), each step a
    :class:`TrainStep` (loss, schedule, ``pieces``, ``autocast``: see there).

    ``eval_fn(model, step)`` runs every ``eval_every`` steps (and after the last step) under ``no_grad`` in eval
    mode; its metrics reach the callbacks. Callbacks run after every step.

    Args:
        pieces: the parts of the step beyond the colour loss (:mod:`recon.nerf.pieces`: sky rays trained empty,
            the sparse-depth prior, per-photo appearance, pose refinement), their terms summed in this order.
        state: a dict from :meth:`TrainProgress.state_dict` to resume from; model, batcher and pieces
            must be constructed as for the original run.
        history_every: record (step, loss, psnr) every this many steps in the result.
        budget_s: > 0: stop once this much training time (evaluation excluded; ``spent_s`` of it
            already used before a resume) is spent; the learning rate then decays with the
            fraction of the budget used, so a budget-bound run still ends at ``lr_final``. A state
            resumed under another budget follows that budget's schedule from ``spent_s`` on, as a
            run given it from the start would (benchmarks/results/fox_budget_resume_plain_share.json).

    Returns a summary dict: step, loss, psnr, rays_per_s, elapsed_s, history, metrics (last eval), and state: the
    finished state less the model's weights and the optimizer's moments (``TrainStep.state_dict(weights=False)``):
    with the weights put back as its "model", ``state=`` trains the finished field on.

    Raises:
        TrainingDiverged: on a NaN/inf loss, naming the step and suggesting a lower rate.
        TrainingInterrupted: on Ctrl-C, carrying a resumable state of the finished steps.
    """
    take_step = TrainStep(model, batcher, steps=steps, lr=lr, lr_final=lr_final, batch_rays=batch_rays,
                          pieces=pieces, autocast=autocast, optimizer=optimizer, beta2=beta2)
    start = 0
    if state is not None:
        take_step.load_state_dict(state)
        start = int(state["step"])
    done = start

    def snapshot() -> dict[str, Any]:
        return {"step": done, **take_step.state_dict()}

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
            result = take_step(step, fraction)
            loss_v, cur_lr = result.loss, result.lr
            done = step + 1
            psnr_v = float(mse_to_psnr(torch.tensor(result.rgb_mse, dtype=torch.float32)))  # as from the float32 loss
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
            "rays_per_s": (done - start) * batch_rays / max(elapsed, 1e-9), "history": history, "metrics": metrics,
            "state": {"step": done, **take_step.state_dict(weights=False)}}
