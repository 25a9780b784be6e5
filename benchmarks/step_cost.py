"""What an option costs a training step, the values' steps interleaved so a busy or throttled host slows all alike.

    python benchmarks/step_cost.py --scene ~/.cache/recon/bench/lego_half_hash_features_cpu/lego-half-fast \\
        --option train.fast.grid --values "dense,hash+train.fast.feature_dim=16+train.fast.feature_res=512" \\
        --out benchmarks/results/lego_half_hash_features_cpu_step_cost.json

A time-budgeted sweep (option_sweep.py) runs one value after the other, so a host that slows down between them (a
shared machine, a CPU's clock) shifts the steps each gets; here every value's training is built on the same scene (its
02_scene, as the train stage plans it: `recon.plans.training`), takes `--warmup` steps (occupancy warm, grids shrunk),
then the values take turns: `--rounds` rounds of `--block` steps each, timed. The record gives each value's
milliseconds a step (the median of its rounds, and the total) and the ratio of each value's total to the first's.
Values as option_sweep's: comma-separated, `VALUE+key=v+...` adds overrides to one. A measurement: it asserts nothing.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_syncs import build_step, scene_row, step_parser  # noqa: E402  (gpu_syncs puts this checkout's recon first)
from option_sweep import split_value  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from recon.atomic import write_json_atomic

    parser = step_parser(__doc__)
    parser.add_argument("--option", required=True, help="a --set key, e.g. train.fast.grid")
    parser.add_argument("--values", required=True, help="comma-separated; VALUE+key=v+... adds overrides to one value")
    turn_arguments(parser, warmup=300)
    args = parser.parse_args(argv)
    row = scene_row("step_cost", args)
    if row is None:
        return 2
    values = args.values.split(",")
    runs = []
    for value in values:
        first, own = split_value(value)
        step, plan, device = build_step(args.scene, args.preset, [*args.set, f"{args.option}={first}", *own])
        for i in range(args.warmup):
            step(i)
        runs.append({"value": value, "step": step, "next": args.warmup})
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    take_turns(runs, args.rounds, args.block, sync)
    row.update({"option": args.option, "device": str(device), "batch_rays": plan.batch_rays, "warmup": args.warmup,
                "rounds": args.rounds, "block": args.block, "values": turn_rows(runs)})
    write_json_atomic(args.out, [row])
    for v in row["values"]:
        print(f"{args.option}={v['value']}: {v['ms_per_step_median']} ms a step (median of {args.rounds} rounds), "
              f"{v['cost_vs_first']}x the first")
    return 0


def turn_arguments(parser: argparse.ArgumentParser, warmup: int) -> None:
    """--warmup, --rounds and --block, for :func:`take_turns`."""
    parser.add_argument("--warmup", type=int, default=warmup, help="untimed steps of each training first")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--block", type=int, default=20, help="steps of one training in a round")


def take_turns(runs: list[dict[str, Any]], rounds: int, block: int, sync: Callable[[], None]) -> None:
    """Each round, each run (its ``step``, from its ``next``) takes ``block`` steps, timed into its ``rounds_ms``;
    a run's ``enter()``, where it has one, is called (untimed) before its turn."""
    for _ in range(rounds):
        for run in runs:
            run.get("enter", lambda: None)()
            sync()
            t0 = time.perf_counter()
            for i in range(run["next"], run["next"] + block):
                run["step"](i)
            sync()
            run.setdefault("rounds_ms", []).append(1000.0 * (time.perf_counter() - t0) / block)
            run["next"] += block


def turn_rows(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each run's ms a step (median and mean of its rounds, the rounds) and its total against the first run's."""
    first_total = sum(runs[0]["rounds_ms"])
    return [{"value": run["value"], "ms_per_step_median": round(statistics.median(run["rounds_ms"]), 2),
             "ms_per_step_mean": round(statistics.fmean(run["rounds_ms"]), 2),
             "rounds_ms": [round(ms, 2) for ms in run["rounds_ms"]],
             "cost_vs_first": round(sum(run["rounds_ms"]) / first_total, 3)} for run in runs]


if __name__ == "__main__":
    sys.exit(main())
