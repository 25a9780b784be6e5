"""The parts of a training step beyond the photos' colour loss, each a piece passed to `recon.nerf.trainer.train`.

Rays known to see nothing (the sky, masked photos' transparent pixels) trained as empty space, the sparse-depth prior,
per-photo appearance and per-photo pose refinement each change the step in a different place; as pieces with a few
hooks the loop stays one loop, a new feature is a new piece instead of new keyword arguments, and whoever builds a
training run (the train stage, the profiler, a benchmark) passes the same sequence. Each step the trainer calls,
piece by piece in the sequence's order:

* ``before_render(batch, at)`` — the batch's rays before the field renders them (pose refinement moves them);
* ``after_render(out, batch)`` — the rendered output before the colour loss (appearance transforms its rgb);
* ``loss_terms(model, out, batch, at)`` — terms added to the loss after the colour terms: the loss sums them in the
  pieces' order, so the same sequence gives the same floating-point sum;
* ``after_step(at)`` — after the field's optimizer stepped (pose refinement steps its own).

``attach(opt, lr)`` runs once, before the first step, with the field's optimizer; ``state_dict()`` returns what a
resume needs under the piece's own keys of the training state, which ``load_state_dict(state)`` reads back.
"""
from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from .appearance import PhotoAppearance
from .pose_refine import PoseRefinement
from .render import RadianceModel

__all__ = ["Appearance", "DepthPriorLoss", "EmptyRays", "PoseRefine", "StepInfo", "TrainPiece", "mixed_precision"]


def mixed_precision(device_type: str, dtype: torch.dtype | None) -> torch.autocast:
    """The step's autocast: ``dtype`` (e.g. bfloat16) for the model's matrix math, or nothing when None."""
    return torch.autocast(device_type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


@dataclass(frozen=True)
class StepInfo:
    """The step a hook runs in: its index (from 0), the run's step count, the share of the time budget spent (when
    a budget sets the schedule, else None) and the autocast dtype the field renders under."""

    step: int
    steps: int
    fraction: float | None
    autocast: torch.dtype | None


class TrainPiece:
    """A part of the training step; every hook does nothing until a piece overrides it."""

    def attach(self, opt: torch.optim.Optimizer, lr: float) -> None:
        """Join the field's optimizer (a parameter group at ``lr``) or set up one's own."""

    def before_render(self, batch: dict[str, Tensor], at: StepInfo) -> dict[str, Tensor]:
        return batch

    def after_render(self, out: dict[str, Any], batch: dict[str, Tensor]) -> dict[str, Any]:
        return out

    def loss_terms(self, model: RadianceModel, out: dict[str, Any], batch: dict[str, Tensor],
                   at: StepInfo) -> dict[str, Tensor]:
        return {}

    def after_step(self, at: StepInfo) -> None:
        """Runs after the field's optimizer stepped."""

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Read this piece's entries of a whole training state (from :meth:`state_dict`)."""


def _copy(module: torch.nn.Module) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


class EmptyRays(TrainPiece):
    """Rays known to see nothing (a batcher's ``empty`` masks: the sky, `recon.capture.sky`, or the transparent pixels
    of masked photos) cost ``weight`` × the batch's mean of their opacity: L1, because a blob coloured like the sky, or
    faint haze over a random background, costs the colour loss almost nothing."""

    def __init__(self, weight: float) -> None:
        self.weight = float(weight)

    def loss_terms(self, model: RadianceModel, out: dict[str, Any], batch: dict[str, Tensor],
                   at: StepInfo) -> dict[str, Tensor]:
        if self.weight <= 0 or "empty" not in batch:
            return {}
        return {"empty": self.weight * (out["opacity"].float() * batch["empty"]).mean()}


class DepthPriorLoss(TrainPiece):
    """A term that renders its own rays, the sparse-depth prior (`recon.nerf.depth_prior.DepthPrior`) or the depth
    smoothness (`recon.nerf.smoothness.PatchSmoothness`): ``prior(model, step) -> {name: loss}``, under the step's
    autocast. It must be deterministic in the step for a resumed run to repeat the uninterrupted one."""

    def __init__(self, prior: Callable[[RadianceModel, int], dict[str, Tensor]]) -> None:
        self.prior = prior

    def loss_terms(self, model: RadianceModel, out: dict[str, Any], batch: dict[str, Tensor],
                   at: StepInfo) -> dict[str, Tensor]:
        with mixed_precision(batch["rgb"].device.type, at.autocast):
            return {k: v.float() for k, v in self.prior(model, at.step).items()}


class Appearance(TrainPiece):
    """Per-photo colour transforms (`recon.nerf.appearance.PhotoAppearance`): each ray's rendered rgb as its photo
    shows it replaces the rgb before the colour loss, the pull towards the identity joins the loss, and the
    transforms are optimized with the field at its rate."""

    def __init__(self, module: PhotoAppearance) -> None:
        self.module = module

    def attach(self, opt: torch.optim.Optimizer, lr: float) -> None:
        opt.add_param_group({"params": list(self.module.parameters()), "lr": lr, "initial_lr": lr})

    def after_render(self, out: dict[str, Any], batch: dict[str, Tensor]) -> dict[str, Any]:
        return {**out, "rgb": self.module(out, batch["image"])}

    def loss_terms(self, model: RadianceModel, out: dict[str, Any], batch: dict[str, Tensor],
                   at: StepInfo) -> dict[str, Tensor]:
        return {"appearance": self.module.regularizer()}

    def state_dict(self) -> dict[str, Any]:
        return {"appearance": _copy(self.module)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.module.load_state_dict(state["appearance"])


class PoseRefine(TrainPiece):
    """Per-photo camera corrections (`recon.nerf.pose_refine.PoseRefinement`): each batch's rays are cast from the
    corrected cameras (near/far re-cut against ``aabb``, the batcher's box, or None), and on the steps
    ``module.learns_at`` the corrections learn: their penalty joins the loss and their own Adam, at the fixed small
    ``module.lr`` (the field's rate schedule would turn cameras 1,000x too fast), steps them, each update followed
    by ``module.hold_frame()``."""

    def __init__(self, module: PoseRefinement, aabb: Tensor | None) -> None:
        self.module, self.aabb = module, aabb
        self.learning = False

    def attach(self, opt: torch.optim.Optimizer, lr: float) -> None:
        self.opt = torch.optim.Adam(self.module.parameters(), lr=self.module.lr)

    def before_render(self, batch: dict[str, Tensor], at: StepInfo) -> dict[str, Tensor]:
        self.learning = self.module.learns_at(at.step, at.steps, at.fraction)
        if self.learning:
            self.opt.zero_grad(set_to_none=True)
        with torch.set_grad_enabled(self.learning):
            return self.module.correct_batch(batch, self.aabb)

    def loss_terms(self, model: RadianceModel, out: dict[str, Any], batch: dict[str, Tensor],
                   at: StepInfo) -> dict[str, Tensor]:
        return {"pose": self.module.regularizer()} if self.learning else {}

    def after_step(self, at: StepInfo) -> None:
        if self.learning:
            self.opt.step()
            self.module.hold_frame()

    def state_dict(self) -> dict[str, Any]:
        return {"pose_refine": _copy(self.module), "pose_optimizer": copy.deepcopy(self.opt.state_dict())}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.module.load_state_dict(state["pose_refine"])
        self.opt.load_state_dict(state["pose_optimizer"])
