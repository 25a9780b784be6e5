"""How many kernels a card's training step launches, counted on a CPU: the host's share of a GPU step.

    python benchmarks/gpu_check.py --out /tmp/gc --smoke --data ../shared/data/nerf_synthetic_lego_half
    python benchmarks/launch_count.py --scene /tmp/gc/lego-fast-default --out benchmarks/results/launch_count.json

A GPU step pays the host for every kernel it launches (Python, the dispatcher, the launch itself), whether or not
the GPU is busy. This counts them without a GPU: the preset is sized as for a card (`recon.config.device_sizing`
with `--memory-gib`), the fast model's Triton kernels run under Triton's interpreter on CPU tensors
(TRITON_INTERPRET=1, as tests/test_triton_kernels.py runs them), the C marcher is off and the view directions'
harmonics are the card's (`recon.nerf.fast.sh_product`), so the step takes the card's code path. After `--warmup` steps in torch (the interpreter is slow), `--steps` steps are counted: every torch
operation that reaches a kernel (views, metadata and allocations left out; those the interpreter makes inside a
Triton kernel left out too), every Triton launch, and the host reads among them, each by the innermost recon function
that asked. The counted steps are those of the middle of a time-budgeted run (`HALFWAY`). The rays a step are
`--rays` (the interpreter's pace), not the card's: what a step launches does not depend on how many rays it takes.
The colour network runs eager here; on a card torch.compile fuses it, so its count here is an upper bound. Steps that refresh the occupancy grid (every 8th) are not counted.

Writes one record (a list of rows, with the commit and machine as every record in benchmarks/results/; `--append`
adds a row to an earlier one). A measurement: it asserts nothing.
"""
from __future__ import annotations

import collections
import json
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

os.environ["TRITON_INTERPRET"] = "1"  # before triton is imported: its kernels then run on CPU tensors
os.environ["RECON_NATIVE"] = "0"  # the C marcher is a CPU's; a card marches in a Triton kernel

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_syncs import scene_row, step_parser  # noqa: E402  (gpu_syncs puts this checkout's recon first)

NO_KERNEL = ("view", "_unsafe_view", "expand", "t", "transpose", "unsqueeze", "squeeze", "select", "slice", "permute",
             "detach", "alias", "as_strided", "reshape", "_reshape_alias", "unbind", "split", "split_with_sizes",
             "lift_fresh", "empty", "empty_like", "empty_strided", "new_empty", "set_", "_record_function_enter_new",
             "_record_function_exit", "scalar_tensor")
"""Operations that launch no kernel on a GPU: views, metadata, allocations, the profiler's markers and the host's
0-dimensional tensors that wrap a Python number (`torch.where(mask, 0.0, x)`)."""
HOST_READS = ("_local_scalar_dense", "nonzero", "item")
"""Operations that make the host wait for the GPU."""
HALFWAY = 0.5
"""The share of a time budget the counted steps take as spent: the rate and the losses (the distortion loss starts
after a tenth of a card's run) are those of the middle of training."""


def recon_place() -> str:
    """The innermost recon function on the stack, as path:function (the part of recon that launched)."""
    for frame in reversed(traceback.extract_stack()):
        if f"{os.sep}recon{os.sep}" in frame.filename:
            return f"{frame.filename.split(f'{os.sep}recon{os.sep}')[-1]}:{frame.name}"
    return "(outside recon)"


class LaunchCounter(TorchDispatchMode):
    """Counts the torch operations that would launch a kernel, by recon place, outside Triton's interpreted kernels."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter[str] = collections.Counter()
        self.places: collections.Counter[str] = collections.Counter()
        self.reads: collections.Counter[str] = collections.Counter()
        self.inside_triton = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = func.overloadpacket.__name__
        if not self.inside_triton and name not in NO_KERNEL:
            self.ops[name] += 1
            place = recon_place()
            self.places[place] += 1
            if name in HOST_READS:
                self.reads[place] += 1
        return func(*args, **(kwargs or {}))


def count(scene_dir: Path, preset: str, overrides: list[str], memory_gib: float, rays: int, warmup: int,
          steps: int) -> dict[str, Any]:
    import triton.runtime.interpreter as interpreter

    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import device_sizing, load_config
    from recon.evaluation.views import load_views
    from recon.nerf import fast, kernels
    from recon.nerf.trainer import TrainStep
    from recon.plans.training import build_training, plan_training

    config = load_config(preset, overrides)
    config, sized = device_sizing(config, int(memory_gib * 2**30), f"a {memory_gib:g} GiB card, simulated")
    cfg = config.train
    card_rays = cfg.batch_rays
    cfg.batch_rays = rays
    cfg.fast.kernels = "triton"
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    views = load_views(scene, scene.split("train"), cfg.max_side)
    device = torch.device("cpu")
    plan = plan_training(cfg, scene, views, device)
    setup = build_training(plan, device)
    step = TrainStep(setup.model, setup.batcher, steps=cfg.steps, **setup.step_kwargs)
    every = cfg.fast.occupancy_every
    first = warmup + (1 if warmup % every == 0 else 0)  # start after a refresh step: it is not counted
    for i in range(first):
        step(i)
    counter = LaunchCounter()
    launches: collections.Counter[str] = collections.Counter()
    run = interpreter.InterpretedFunction.run

    def counted_run(self: Any, *args: Any, **kwargs: Any) -> Any:
        launches[self.fn.__name__] += 1
        counter.inside_triton += 1
        try:
            return run(self, *args, **kwargs)
        finally:
            counter.inside_triton -= 1

    kernels.KERNEL_DEVICES = ("cuda", "cpu")
    if cfg.fast.grid == "hash":  # the train stage probes the hash grid's kernel once, as it plans: not in a step
        from recon.nerf.grid import hash_kernel_check

        grid = setup.model.color_grid  # the probe is the grid's own levels and features, as the train stage's
        hash_kernel_check("cpu", grid.levels, grid.features)
    sh_encode = fast.sh_encode
    # a card's harmonics (a CPU runs the terms); code from before sh_product had only the terms, on every device
    fast.sh_encode = getattr(fast, "sh_product", sh_encode)
    for degree in range(4):  # their matrices are made once, at a run's first step, not at every step
        fast.sh_encode(torch.zeros(1, 3), degree)
    interpreter.InterpretedFunction.run = counted_run
    taken, i, t0 = 0, first, time.perf_counter()
    try:
        with counter:
            while taken < steps:
                if i % every:
                    step(i, HALFWAY)
                    taken += 1
                else:  # an occupancy refresh: not counted
                    with _Paused(counter):
                        step(i, HALFWAY)
                i += 1
    finally:
        interpreter.InterpretedFunction.run = run
        kernels.KERNEL_DEVICES = ("cuda",)
        fast.sh_encode = sh_encode

    def per_step(c: collections.Counter[str]) -> dict[str, float]:
        return {k: round(v / steps, 2) for k, v in c.most_common()}

    torch_ops = sum(counter.ops.values()) / steps
    triton = sum(launches.values()) / steps
    return {"device": "cpu (Triton interpreter, the card's code path)", "sized": sized, "card_batch_rays": card_rays,
            "counted_batch_rays": rays, "warmup": first, "counted_steps": steps,
            "distortion_loss_on": bool(getattr(setup.model, "distortion_weight_now", lambda: 0)() > 0),
            "launches_per_step": round(torch_ops + triton, 2), "torch_ops_per_step": round(torch_ops, 2),
            "triton_launches_per_step": round(triton, 2),
            "host_reads_per_step": round(sum(counter.reads.values()) / steps, 2),
            "ops": per_step(counter.ops), "places": per_step(counter.places), "triton": per_step(launches),
            "host_reads": per_step(counter.reads), "seconds": round(time.perf_counter() - t0, 1)}


class _Paused:
    """Leaves a step uncounted (the counter sees it as inside a kernel) and runs it in torch (the interpreter would
    take minutes over an occupancy refresh's grid)."""

    def __init__(self, counter: LaunchCounter) -> None:
        self.counter = counter

    def __enter__(self) -> None:
        from recon.nerf import kernels

        self.counter.inside_triton += 1
        kernels.KERNEL_DEVICES = ("cuda",)

    def __exit__(self, *exc: Any) -> None:
        from recon.nerf import kernels

        self.counter.inside_triton -= 1
        kernels.KERNEL_DEVICES = ("cuda", "cpu")


def main(argv: list[str] | None = None) -> int:
    from recon.atomic import write_json_atomic

    parser = step_parser(__doc__)
    parser.add_argument("--memory-gib", type=float, default=80.0, help="the card's memory, for the sizing (an H100: 80)")
    parser.add_argument("--rays", type=int, default=64, help="rays a counted step (the interpreter's pace)")
    parser.add_argument("--warmup", type=int, default=80, help="steps before counting")
    parser.add_argument("--steps", type=int, default=3, help="steps counted")
    parser.add_argument("--append", action="store_true", help="add the row to --out's rows instead of replacing them")
    args = parser.parse_args(argv)
    row = scene_row("launch_count", args)
    if row is None:
        return 2
    row.update(count(args.scene, args.preset, args.set, args.memory_gib, args.rays, args.warmup, args.steps))
    earlier = json.loads(args.out.read_text()) if args.append and args.out.is_file() else []
    write_json_atomic(args.out, [*earlier, row])
    print(f"{row['launches_per_step']:.0f} launches a step ({row['torch_ops_per_step']:.0f} torch operations, "
          f"{row['triton_launches_per_step']:.0f} Triton kernels), {row['host_reads_per_step']:.0f} host reads")
    for place, n in row["places"].items():
        print(f"{n:7.1f}  {place}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
