"""Adam that leaves a dense grid's untouched entries alone (DVGO's masked Adam), its update in C on a CPU.

A step's rays read a few percent of a dense grid's entries; the rest get a gradient of exactly 0. torch's Adam still
moves every one of them (their moments decay and keep pushing) and reads and writes four arrays of the grids' size
for it: on a CPU that pass over tens of millions of values is one of the largest parts of a step. In a parameter
group marked ``masked`` (the fast model's grids), :class:`MaskedAdam` updates only the values whose gradient is not
0: an entry no ray touched keeps its value and its moments, as DVGO's masked Adam does (Sun et al. 2022). Other
groups (the colour network) get torch's Adam update. Without weight decay or amsgrad, which recon does not use.

:func:`adam_step_torch` is the reference; :func:`recon.nerf.native.adam_native` the same update in C (blocks of values
without a gradient are skipped after one look), used for float32 CPU tensors when the native library loaded. Where
the grids' C backward flagged the blocks it added into (:class:`TouchedBlocks`), the update visits only those: a
step's rays reach few of a fine grid's blocks, and the gradients of the others need not be read to know they are 0.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import Tensor

from recon.nerf.native import adam_blocks, adam_native

__all__ = ["MaskedAdam", "TouchedBlocks", "adam_step_torch", "touched_blocks"]


def adam_step_torch(param: Tensor, grad: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, *, beta1: float, beta2: float,
                    step_size: float, bias2_sqrt: float, eps: float, masked: bool) -> None:
    """One Adam update in place, as torch.optim.Adam computes it (``step_size = lr / (1 - beta1^t)``,
    ``bias2_sqrt = sqrt(1 - beta2^t)``); where ``masked``, values whose gradient is exactly 0 keep value and moments."""
    m_new = exp_avg + (grad - exp_avg) * (1.0 - beta1)
    v_new = exp_avg_sq * beta2 + (1.0 - beta2) * grad * grad
    p_new = param - step_size * m_new / (v_new.sqrt() / bias2_sqrt + eps)
    if masked:
        touched = grad != 0
        m_new, v_new, p_new = (torch.where(touched, new, old) for new, old in
                               ((m_new, exp_avg), (v_new, exp_avg_sq), (p_new, param)))
    exp_avg.copy_(m_new)
    exp_avg_sq.copy_(v_new)
    param.copy_(p_new)


class TouchedBlocks:
    """Which blocks of :data:`recon.nerf.native.ADAM_BLOCK` values of a parameter's gradient may hold a non-zero
    value: a flag per block, set by the grids' C backward where it adds, cleared by :class:`MaskedAdam`'s C update as
    it visits them.

    The flags speak for one gradient tensor at one version (:meth:`valid_for`): any other writer into the gradient (a
    torch read's autograd, a regularizer) changes its version, and the update then looks at every block, after which
    the gradient is all 0 and the flags, cleared, are valid again."""

    def __init__(self, numel: int) -> None:
        self.flags = torch.zeros(adam_blocks(numel), dtype=torch.uint8)
        self._for: tuple[Tensor, int] | None = None

    def valid_for(self, grad: Tensor) -> bool:
        """Whether the flags cover every non-zero block of ``grad``: it is the tensor vouched for, unchanged since."""
        return self._for is not None and self._for[0] is grad and self._for[1] == grad._version

    def vouch(self, grad: Tensor) -> None:
        """The flags cover every non-zero block of ``grad`` as it is now."""
        self._for = (grad, grad._version)

    def reset(self, grad: Tensor) -> None:
        """``grad`` is all 0: clear the flags, and vouch for it."""
        self.flags.zero_()
        self.vouch(grad)


def touched_blocks(param: Tensor) -> TouchedBlocks:
    """The parameter's :class:`TouchedBlocks` (made on first use, and again if the parameter changed size)."""
    touched = getattr(param, "touched_blocks", None)
    if touched is None or touched.flags.numel() != adam_blocks(param.numel()):
        touched = TouchedBlocks(param.numel())
        param.touched_blocks = touched  # type: ignore[attr-defined]
    return touched


class MaskedAdam(torch.optim.Optimizer):
    """Adam whose parameter groups marked ``"masked": True`` update only the values that have a gradient.

    State per parameter as torch.optim.Adam keeps it (``step``, ``exp_avg``, ``exp_avg_sq``), so its checkpoints
    look like Adam's; ``step`` counts the optimizer's steps (the bias correction), not a value's own updates.

    The C update of a masked parameter also sets the gradient values it used to 0, and :meth:`zero_grad` then keeps
    that all-zero gradient instead of dropping it (when nothing changed it since): the next backward adds into it,
    and a dense grid's C backward skips zeroing a buffer of the grid's size every step. Results are the same."""

    def __init__(self, params: Iterable[Any], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        if lr < 0 or eps < 0 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"MaskedAdam needs lr >= 0, eps >= 0 and betas in [0, 1); got {lr}, {eps}, {betas}")
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps, "masked": False})
        self._zeroed: dict[int, tuple[Tensor, int]] = {}
        """id(param) -> (its gradient, that gradient's version) where the last step left it all 0."""

    def zero_grad(self, set_to_none: bool = True) -> None:
        """torch's zero_grad, except that a gradient the last step left all 0 (and nothing touched since) is kept."""
        zeroed, self._zeroed = self._zeroed, {}
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                kept = zeroed.get(id(p))
                if kept is not None and kept[0] is p.grad and kept[1] == p.grad._version:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().requires_grad_(False)
                    p.grad.zero_()

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.grad.is_sparse:
                    raise RuntimeError("MaskedAdam takes dense gradients (a value without one has a gradient of 0)")
                state = self.state[p]
                if not state:
                    state["step"] = torch.tensor(0.0)
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["step"] += 1
                t = float(state["step"])
                kwargs = {"beta1": beta1, "beta2": beta2, "step_size": group["lr"] / (1.0 - beta1**t),
                          "bias2_sqrt": math.sqrt(1.0 - beta2**t), "eps": group["eps"],
                          "masked": bool(group.get("masked", False))}
                touched = getattr(p, "touched_blocks", None) if kwargs["masked"] else None
                flags = touched.flags if touched is not None and touched.valid_for(p.grad) else None
                if adam_native(p, p.grad, state["exp_avg"], state["exp_avg_sq"], clear=kwargs["masked"], touched=flags,
                               **kwargs):
                    if kwargs["masked"]:
                        self._zeroed[id(p)] = (p.grad, p.grad._version)
                        if touched is not None and flags is not None:  # the update cleared each flag it visited
                            touched.vouch(p.grad)  # and the gradient is all 0 now
                        elif touched is not None:  # it looked at every block: flags from before may be left
                            touched.reset(p.grad)
                else:
                    adam_step_torch(p, p.grad, state["exp_avg"], state["exp_avg_sq"], **kwargs)
        return loss
