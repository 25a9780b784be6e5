"""What one option buys: the same capture, the same SfM and masks, a preset trained once per value of the option,
one run after the other (so the rows compare).

    python benchmarks/option_sweep.py --option train.fast.distortion_weight --values 0,0.03 --data sample \
        --name sample_distortion
    python benchmarks/option_sweep.py --option train.transparent_weight --values 0,0.1 --data fox --until train \
        --name transparent_weight

A value may bring overrides of its own after "+" (what only that value needs), e.g.
`--values dense,hash+train.fast.feature_res=512` for a hash grid of finer levels than the dense grid's resolution.

Runs poses and normalize once (`recon bench`'s shared scene, automatic masks included), then `recon bench`'s run of
`--preset` once per value on that scene: steps, rays/s, held-out PSNR overall and per test photo, and with
`--until mesh` (the default) the mesh's accuracy where the data has a true surface. Writes
benchmarks/results/<name>.json after each value. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def split_value(item: str) -> tuple[str, list[str]]:
    """One of --values, `VALUE+key=v+...`: (VALUE, its own overrides [key=v, ...])."""
    value, *own = item.split("+")
    return value, own


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--option", required=True, help="a --set key, e.g. train.fast.distortion_weight")
    parser.add_argument("--values", required=True,
                        help="comma-separated values, run in this order; VALUE+key=v+... adds overrides to one value")
    parser.add_argument("--data", default="sample")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--until", default="mesh", choices=["train", "mesh"])
    parser.add_argument("--set", action="append", default=[], help="more overrides, the same for every value")
    parser.add_argument("--name", required=True, help="the record: benchmarks/results/<name>.json")
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: ~/.cache/recon/bench/<name>)")
    args = parser.parse_args()

    from recon.app.bench import run_bench
    from recon.app.progress import Reporter
    from recon.atomic import write_json_atomic

    result = REPO / "benchmarks" / "results" / f"{args.name}.json"
    work = args.work or Path.home() / ".cache" / "recon" / "bench" / args.name
    report = Reporter(quiet=True)
    rows: list[dict[str, Any]] = []
    for item in args.values.split(","):
        value, own = split_value(item)
        overrides = [*args.set, f"{args.option}={value}", *own]
        row = run_bench(args.data, [args.preset], work, overrides, report, until=args.until)[0]
        metrics = json.loads((work / f"{Path(args.data).name}-{args.preset}" / "03_field" / "metrics.json").read_text())
        row["option"], row["value"] = args.option, value
        if own:
            row["value_overrides"] = own
        row["psnr_per_view"] = {v["view"]: round(v["psnr"], 2) for v in metrics["test"]["views"]}
        if "psnr_neutral" in metrics["test"]:  # with per-photo appearance: the neutral render on the whole photo
            row["psnr_neutral"] = round(metrics["test"]["psnr_neutral"], 2)
        rows.append(row)
        mesh = f", F@1% {row['fscore_1pct']:.3f}" if row.get("fscore_1pct") is not None else ""
        print(f"{args.option}={item}: {row['steps']} steps, {row['rays_per_s']:,.0f} rays/s, "
              f"test PSNR {row['psnr']:.2f} dB{mesh}")
        write_json_atomic(result, rows)
    print(f"wrote {result}")


if __name__ == "__main__":
    main()
