"""What training masked photos' transparent pixels as empty space buys: the same capture, the same SfM and masks,
`fast` with `train.transparent_weight` 0 (random backgrounds alone) against the shipped value.

    python benchmarks/transparent_weight.py [--data fox] [--weights 0,0.1] [--work DIR]

Runs poses and normalize once (`recon bench`'s shared scene, automatic masks included), then `recon bench`'s `fast`
run once per weight, one after the other, on that scene: steps, rays/s, held-out PSNR overall and per test photo
(each photo's appearance fitted on its left half, its right half scored). Writes
benchmarks/results/transparent_weight.json. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one

RESULT = REPO / "benchmarks" / "results" / "transparent_weight.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="fox")
    parser.add_argument("--weights", default="0,0.1")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "recon" / "bench" / "transparent_weight")
    args = parser.parse_args()

    from recon.app.bench import run_bench
    from recon.app.progress import Reporter
    from recon.atomic import write_json_atomic

    report = Reporter(quiet=True)
    rows: list[dict[str, Any]] = []
    for weight in [float(w) for w in args.weights.split(",")]:
        overrides = [f"train.transparent_weight={weight:g}"]
        row = run_bench(args.data, ["fast"], args.work, overrides, report, until="train")[0]
        metrics = json.loads((args.work / f"{Path(args.data).name}-fast" / "03_field" / "metrics.json").read_text())
        row["transparent_weight"] = weight
        row["psnr_per_view"] = {v["view"]: round(v["psnr"], 2) for v in metrics["test"]["views"]}
        rows.append(row)
        print(f"transparent_weight {weight:g}: {row['steps']} steps, {row['rays_per_s']:,.0f} rays/s, "
              f"test PSNR {row['psnr']:.2f} dB {row['psnr_per_view']}")
        write_json_atomic(RESULT, rows)
    print(f"wrote {RESULT}")


if __name__ == "__main__":
    main()
