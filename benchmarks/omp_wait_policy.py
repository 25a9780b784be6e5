"""What OpenMP's wait policy costs a CPU training step: OMP_WAIT_POLICY=PASSIVE against libgomp's default.

    python benchmarks/omp_wait_policy.py --scene DIR --pairs 5 --out benchmarks/results/sample_omp_wait_policy.json

The policy is read once, when torch loads OpenMP, so each measurement is a process of its own: `step_cost.py` on the
scene (`--warmup` untimed steps, then `--rounds` of `--block` timed steps; ms a step is their median), with
OMP_WAIT_POLICY=PASSIVE or without the variable (libgomp's default: a thread spins briefly after a parallel region,
then sleeps). The processes alternate in the order A B B A A B ..., so a host that drifts slows both alike. The record
gives every process's ms a step, each policy's mean, and their ratio. A measurement: it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
POLICIES = ("PASSIVE", "default")


def one_process(policy: str, args: argparse.Namespace, out: Path) -> float:
    """ms a step (median of its rounds) of one step_cost.py process under `policy`."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy != "default":
        env["OMP_WAIT_POLICY"] = policy
    command = [sys.executable, str(REPO / "benchmarks" / "step_cost.py"), "--scene", str(args.scene), "--preset",
               args.preset, "--option", "train.fast.grid", "--values", "dense", "--warmup", str(args.warmup),
               "--rounds", str(args.rounds), "--block", str(args.block), "--out", str(out)]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"step_cost.py failed under {policy}: {done.stderr[-1500:]}")
    return float(json.loads(out.read_text())[0]["values"][0]["ms_per_step_median"])


def main(argv: list[str] | None = None) -> int:
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="a scene folder recon made (its 02_scene is read)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--pairs", type=int, default=5, help="processes per policy")
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--block", type=int, default=20)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if not (args.scene / "02_scene").is_dir() or args.pairs < 1:
        print(f"error: --scene needs a recon scene folder with 02_scene ({args.scene}) and --pairs >= 1", file=sys.stderr)
        return 2
    row: dict[str, Any] = {"name": "omp_wait_policy", "scene": str(args.scene), "preset": args.preset,
                           "warmup": args.warmup, "rounds": args.rounds, "block": args.block,
                           "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **provenance(),
                           "load_average_start": [round(x, 2) for x in os.getloadavg()]}
    order = [POLICIES[(i + 1) // 2 % 2] for i in range(2 * args.pairs)]  # A B B A A B B A ...
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, policy in enumerate(order):
            ms = one_process(policy, args, Path(tmp) / f"{i}.json")
            runs.append({"policy": policy, "ms_per_step": ms})
            print(f"{i + 1}/{len(order)} {policy}: {ms} ms a step", flush=True)
    row["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    means = {p: round(statistics.mean(r["ms_per_step"] for r in runs if r["policy"] == p), 2) for p in POLICIES}
    row.update(runs=runs, mean_ms_per_step=means, passive_vs_default=round(means["PASSIVE"] / means["default"], 3))
    write_json_atomic(args.out, [row])
    print(f"mean ms a step: {means}; PASSIVE / default = {row['passive_vs_default']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
