"""The fast preset's sample culling at equal training time: the culling thresholds given with ``--before`` (each a
``train.fast.KEY=VALUE``) against the shipped defaults, on the fox trained unbounded (masks off: the room as well as
the fox) and on the half-size Lego (bounded), one after the other in one process.

    python benchmarks/sample_culling.py [--budget 150] [--work DIR] [--before KEY=VALUE ...]

Each run trains for ``--budget`` wall seconds as the train stage would (recon.plans.training: the same model, rays
and step pieces; the learning rate follows the budget's fraction spent), then renders held-out views: 4 of the fox's
validation photos (each photo's colour transform fitted on its left half, its right half scored, as the train stage
scores them) and 8 of the Lego's 200 test views. Rows: steps, rays/s (wall), samples and colored samples per ray,
training PSNR over the last 50 steps and held-out PSNR. Writes benchmarks/results/sample_culling.json.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from unbounded_march import FOX, REPO, build, counting_colored

RESULT = REPO / "benchmarks" / "results" / "sample_culling.json"
BEFORE = ["train.fast.occupancy_alpha=0.02", "train.fast.unbounded_occupancy_alpha=0.02",
          "train.fast.color_min_weight=1e-4", "train.fast.early_stop_transmittance=1e-4"]


def run(data: str, work: Path, overrides: list[str], budget: float) -> dict[str, Any]:
    """Train ``data`` (fox: unbounded, masks off; lego-half: bounded) for ``budget`` seconds, then score held-out views."""
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import evaluate, load_views

    torch.manual_seed(0)
    fox = data == "fox"
    setup = build(str(FOX), work, ["normalize.masks=off", *overrides], unbounded=True) if fox \
        else build("lego-half", work, overrides)
    model, take_step, rays = setup["model"], setup["take_step"], setup["rays"]
    per_step: list[tuple[float, float]] = []
    with counting_colored(model) as colored:
        t0, c0, step = time.perf_counter(), time.process_time(), 0
        while (elapsed := time.perf_counter() - t0) < budget:
            result = take_step(step, elapsed / budget)
            per_step.append((result.out["num_samples"] / rays, float(-10 * np.log10(result.rgb_mse))))
            step += 1
        train_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    scene_dir = work / ("fox-poses" if fox else "lego-half-poses")
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    views = load_views(scene, scene.split("val")[::2] if fox else scene.split("test")[::25],
                       load_config("fast").train.max_side)
    model.eval()
    with torch.no_grad():
        # the background the train stage plans and scores with (an unbounded capture's: the photos' border colour)
        held = evaluate(model, views, None if fox else model.aabb, np.asarray(setup["background"], np.float32), appearance=fox)
    return {"steps": step, "train_time_s": round(train_s, 1), "cpu_s_per_step": round(cpu_s / step, 4),
            "rays_per_s": round(step * rays / train_s, 1),
            "samples_per_ray": round(statistics.mean(s for s, _ in per_step[-50:]), 2),
            "colored_per_ray": round(sum(colored) / step / rays, 2),
            "train_psnr_last50": round(statistics.mean(p for _, p in per_step[-50:]), 3),
            "psnr": round(held["psnr"], 3), "psnr_of": (f"{len(views)} validation photos' right halves (appearance "
                                                       "fitted on the left)" if fox else f"{len(views)} test views")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budget", type=float, default=150.0, help="training seconds per run")
    parser.add_argument("--work", type=Path, default=None, help="folder for the prepared scenes (default: a temp dir)")
    parser.add_argument("--before", nargs="*", default=BEFORE, help="the culling settings to compare the defaults with")
    args = parser.parse_args()
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic

    work = args.work or Path(tempfile.mkdtemp(prefix="recon-sample-culling-"))
    rows = []
    for data in ("fox", "lego-half"):
        for name, overrides in (("before", list(args.before)), ("defaults", [])):
            load_start = [round(x, 2) for x in os.getloadavg()]
            result = run(data, work, overrides, args.budget)
            rows.append({"name": f"{data}_{name}", **provenance(),
                         "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                         "load_average_start": load_start, "load_average_end": [round(x, 2) for x in os.getloadavg()],
                         "data": f"{FOX} (reference poses, masks off, trained unbounded)" if data == "fox"
                         else "lego-half (bounded)", "preset": "fast", "overrides": overrides,
                         "budget_s": args.budget, **result})
            print(json.dumps(rows[-1]), flush=True)
    write_json_atomic(RESULT, rows)
    print(f"record: {RESULT}")


if __name__ == "__main__":
    main()
