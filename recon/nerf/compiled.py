"""torch.compile for the fast model's colour network on CUDA, the eager network kept as the reference.

On a GPU the fast model's step is launch-bound: every per-sample op is its own small kernel. The colour MLP
(linear, ReLU, linear, ..., sigmoid) runs on every coloured sample of every step; compiled, its bias, activation and
the final sigmoid fuse into the matmuls' kernels. Only the module's `forward` is replaced (by a compiled function of
ours: `nn.Module.compile` compiles a frame of torch.nn, which torch.compile leaves uncompiled): parameters,
`state_dict` keys, checkpoints and saved fields stay those of the eager module, which stays the reference the
compiled one is tested against (tests/test_devices.py). The sample count changes every step, so the batch dimension
is compiled as dynamic (one graph, not one per shape).

Not compiled: the SDF network of the surface model (its Eikonal and curvature terms take gradients of gradients,
which compiled graphs do not support), the grids and the marcher (data-dependent shapes and host reads break the
graph; the CPU's C marcher, recon/nerf/native.py, is faster there anyway). On a CPU, `auto` leaves everything eager:
compiling costs a minute of a budget measured in minutes and the fused CPU kernels gain little on 64-wide layers.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import torch
from torch import nn

__all__ = ["compile_color_network", "compile_wanted"]

CompileSetting = Literal["auto", "on", "off"]


def compile_wanted(setting: CompileSetting, device: torch.device) -> tuple[bool, str]:
    """(compile?, why) for train.compile = `setting` on `device`: auto means on CUDA only."""
    if setting == "off":
        return False, "torch.compile: off (train.compile=off)"
    if setting == "auto" and device.type != "cuda":
        return False, f"torch.compile: off on {device.type} (train.compile=auto compiles on CUDA only)"
    return True, f"torch.compile: the colour network (train.compile={setting})"


def compile_color_network(model: nn.Module, device: torch.device, setting: CompileSetting = "auto",
                          backend: str | Callable[..., Any] = "inductor") -> str:
    """Compile `model.color_mlp` in place when `compile_wanted` says so; returns the line saying what was done.

    The compiled network runs once on a few samples here, so a compiler that fails (no Triton, an unsupported GPU)
    is found now and the network stays eager, said in the returned line, instead of failing mid-training."""
    wanted, why = compile_wanted(setting, device)
    mlp = getattr(model, "color_mlp", None)
    if not wanted:
        return why
    if not isinstance(mlp, nn.Sequential):
        return "torch.compile: nothing to compile (the colour model has no MLP)"
    first = next(m for m in mlp if isinstance(m, nn.Linear))
    probe = torch.rand(7, first.in_features, device=device)
    with torch.no_grad():
        reference = mlp(probe)
    grad_probe = torch.rand(64, first.in_features, device=device, requires_grad=True)
    reference_grads = _input_and_weight_grads(mlp, grad_probe)
    eager = mlp.forward

    def forward(x: torch.Tensor) -> torch.Tensor:  # a frame of ours: dynamo traces it, inlining the Sequential's
        return eager(x)

    try:
        mlp.forward = torch.compile(forward, backend=backend, dynamic=True)
        with torch.no_grad():
            compiled = mlp(probe)
        torch.testing.assert_close(compiled, reference, rtol=1e-3, atol=1e-4)
        # the training graph (forward and backward, features that need a gradient) compiles here, not in the
        # first step of a time-budgeted training
        for got, want in zip(_input_and_weight_grads(mlp, grad_probe), reference_grads, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-4)
    except Exception as exc:  # any compiler failure: the eager network is correct, only slower
        del mlp.forward  # back to the class's eager forward
        return f"torch.compile: failed ({type(exc).__name__}: {str(exc).splitlines()[0][:160]}); the colour network stays eager"
    return why + f", {getattr(backend, '__name__', backend)}, dynamic sample counts; the eager network is its reference"


def _input_and_weight_grads(mlp: nn.Module, x: torch.Tensor) -> list[torch.Tensor]:
    """The gradients of ``mlp(x).sum()`` for ``x`` and each parameter (``autograd.grad``: no ``.grad`` is touched)."""
    return list(torch.autograd.grad(mlp(x).sum(), [x, *mlp.parameters()]))
