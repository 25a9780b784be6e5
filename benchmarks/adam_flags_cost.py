"""What MaskedAdam's block flags save a CPU training step: the same training twice, its steps taken in turns, one
visiting only the blocks the grids' C backward flagged, the other looking at every block's gradient.

    python benchmarks/adam_flags_cost.py --scene ~/.cache/recon/bench/sample_hash_features_cpu/sample-fast \\
        --warmup 600 --out benchmarks/results/sample_adam_flags_step_cost.json

Both trainings are built as the train stage builds them (`recon.plans.training`) on the scene's 02_scene and take
`--warmup` steps each; then they take turns, `--rounds` rounds of `--block` steps (step_cost.py's `take_turns`), the
flags switched off for the second's turns (`TouchedBlocks.valid_for` answering no, as it does after a write the flags
did not see: the update then looks at every block). The two give the same values bit for bit
(tests/test_masked_adam.py); the record gives each one's ms a step and the ratio, and the share of each grid's blocks
flagged in one more step. A measurement: it asserts nothing.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_syncs import build_step, scene_row, step_parser  # noqa: E402  (gpu_syncs puts this checkout's recon first)
from step_cost import take_turns, turn_arguments, turn_rows  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from recon.atomic import write_json_atomic
    from recon.nerf.masked_adam import MaskedAdam, TouchedBlocks

    parser = step_parser(__doc__)
    turn_arguments(parser, warmup=600)
    args = parser.parse_args(argv)
    row = scene_row("adam_flags_cost", args)
    if row is None:
        return 2
    flagged = TouchedBlocks.valid_for
    switches = {"flagged blocks": flagged, "every block": lambda self, grad: False}
    runs = []
    for value, valid_for in switches.items():
        step, plan, device = build_step(args.scene, args.preset, args.set)
        if not isinstance(step.opt, MaskedAdam):
            print(f"error: {args.preset} trains with {type(step.opt).__name__} here, not MaskedAdam: nothing to "
                  "compare (a CPU with the native library takes MaskedAdam)", file=sys.stderr)
            return 2

        def enter(valid_for=valid_for) -> None:
            TouchedBlocks.valid_for = valid_for

        enter()
        for i in range(args.warmup):
            step(i)
        runs.append({"value": value, "step": step, "next": args.warmup, "enter": enter})
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    try:
        take_turns(runs, args.rounds, args.block, sync)
    finally:
        TouchedBlocks.valid_for = flagged
    row.update({"device": str(device), "batch_rays": plan.batch_rays, "warmup": args.warmup, "rounds": args.rounds,
                "block": args.block, "values": turn_rows(runs), "flagged_share": flagged_share(runs[0])})
    write_json_atomic(args.out, [row])
    for v in row["values"]:
        print(f"{v['value']}: {v['ms_per_step_median']} ms a step (median of {args.rounds} rounds), "
              f"{v['cost_vs_first']}x the first")
    for grid in row["flagged_share"]:
        print(f"grid {grid['shape']}: {grid['blocks_flagged']:.1%} of its blocks flagged")
    return 0


def flagged_share(run: dict[str, Any]) -> list[dict[str, Any]]:
    """One more step of the flagged training, its update watched: each masked parameter's shape and the share of its
    blocks flagged (what the update visits) as the update starts."""
    from recon.nerf.masked_adam import MaskedAdam

    seen: list[dict[str, Any]] = []
    update = MaskedAdam.step

    def watched(self: MaskedAdam, closure: Any = None) -> Any:
        for group in self.param_groups:
            for p in group["params"] if group.get("masked") else []:
                touched = getattr(p, "touched_blocks", None)
                if p.grad is not None and touched is not None and touched.valid_for(p.grad):
                    seen.append({"shape": list(p.shape), "blocks_flagged": round(touched.flags.float().mean().item(), 4)})
        return update(self, closure)

    MaskedAdam.step = watched  # type: ignore[method-assign]
    try:
        run["step"](run["next"])
    finally:
        MaskedAdam.step = update  # type: ignore[method-assign]
    return seen


if __name__ == "__main__":
    sys.exit(main())
