"""Where a CUDA training step waits for the GPU: the host reads of a few steps, by the recon lines that made them.

    python benchmarks/gpu_check.py --out /tmp/gc                       # makes /tmp/gc/lego-fast-default
    python benchmarks/gpu_syncs.py --scene /tmp/gc/lego-fast-default --out /tmp/gc/gpu_syncs.json

Plans and builds training on a scene recon made (its 02_scene) as the train stage does (`recon.plans.training`), takes
`--warmup` steps (occupancy warm, grids shrunk), then `--steps` steps under `torch.cuda.set_sync_debug_mode("warn")`:
every operation that makes the host wait for the GPU warns, and each warning's recon stack frames name where it came
from. Then `--timed` steps are timed (the device synchronized at both ends): milliseconds a step without the train
stage's callbacks. Writes one record (a list of one row, with the commit and machine as every record in
benchmarks/results/). A measurement: it asserts nothing. On a CPU there is nothing to wait for: it times the steps only.
"""
from __future__ import annotations

import argparse
import collections
import os
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon (its commit is the one recorded)


def recon_frames(depth: int = 4) -> str:
    """The innermost `depth` frames of the current stack inside recon, innermost first, as path:line(function)."""
    frames = [f for f in traceback.extract_stack() if f"{os.sep}recon{os.sep}" in f.filename]
    return " <- ".join(f"{f.filename.split(f'{os.sep}recon{os.sep}')[-1]}:{f.lineno}({f.name})"
                       for f in reversed(frames[-depth:]))


def build_step(scene_dir: Path, preset: str, overrides: list[str]) -> tuple[Any, Any, torch.device]:
    """(a training step taking its index, the training plan, the device) for a preset with overrides on a scene recon
    made, planned and built as the train stage does; on CUDA its kernels compiled (`warm_up`)."""
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config
    from recon.evaluation.views import load_views
    from recon.nerf.device import select_device
    from recon.nerf.trainer import TrainStep, warm_up
    from recon.plans.training import build_training, plan_training

    cfg = load_config(preset, overrides).train
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    views = load_views(scene, scene.split("train"), cfg.max_side)
    device = select_device(cfg.device)
    plan = plan_training(cfg, scene, views, device)
    setup = build_training(plan, device)
    if device.type == "cuda":
        warm_up(setup.model, setup.batcher, plan.batch_rays, plan.autocast)
    return TrainStep(setup.model, setup.batcher, steps=cfg.steps, **setup.step_kwargs), plan, device


def measure(scene_dir: Path, preset: str, overrides: list[str], warmup: int, steps: int, timed: int) -> dict[str, Any]:
    step, plan, device = build_step(scene_dir, preset, overrides)
    cuda = device.type == "cuda"
    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    for i in range(warmup):
        step(i)
    sync()
    places: collections.Counter[str] = collections.Counter()
    if cuda:
        shown = warnings.showwarning
        warnings.showwarning = lambda *args, **kwargs: places.update([recon_frames()])
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
                for i in range(warmup, warmup + steps):
                    step(i)
        finally:
            torch.cuda.set_sync_debug_mode(0)
            warnings.showwarning = shown
    sync()
    t0 = time.perf_counter()
    for i in range(warmup + steps, warmup + steps + timed):
        step(i)
    sync()
    ms = 1000.0 * (time.perf_counter() - t0) / max(1, timed)
    return {"device": str(device), "batch_rays": plan.batch_rays, "warmup": warmup, "debugged_steps": steps if cuda else 0,
            "host_reads_per_step": round(sum(places.values()) / steps, 2) if cuda else None,
            "places": dict(places.most_common()), "timed_steps": timed, "ms_per_step": round(ms, 2)}


def step_parser(doc: str) -> argparse.ArgumentParser:
    """The options of a script that measures training steps on a scene recon made (this one, launch_count.py)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="a scene folder recon made (its 02_scene is read)")
    parser.add_argument("--out", type=Path, required=True, help="the record to write (JSON)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override, as recon --set")
    return parser


def scene_row(name: str, args: argparse.Namespace) -> dict[str, Any] | None:
    """A record row's provenance (the scene and options, date, commit, machine, load), or None, said on stderr, when
    ``args.scene`` holds no scene recon made."""
    from recon.app.bench import provenance

    if not (args.scene / "02_scene" / "scene.json").is_file():
        print(f"error: {args.scene} has no 02_scene/scene.json: pass --scene with a scene folder recon made "
              "(e.g. one the GPU check left in its --out)", file=sys.stderr)
        return None
    return {"name": name, "scene": str(args.scene), "preset": args.preset, "overrides": args.set,
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **provenance(),
            "load_average_start": [round(x, 2) for x in os.getloadavg()]}


def main(argv: list[str] | None = None) -> int:
    from recon.atomic import write_json_atomic

    parser = step_parser(__doc__)
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--steps", type=int, default=3, help="steps under the sync debug mode")
    parser.add_argument("--timed", type=int, default=100)
    args = parser.parse_args(argv)
    row = scene_row("gpu_syncs", args)
    if row is None:
        return 2
    row.update(measure(args.scene, args.preset, args.set, args.warmup, args.steps, args.timed))
    write_json_atomic(args.out, [row])
    print(f"{row['device']}: {row['ms_per_step']} ms a step of {row['batch_rays']:,} rays"
          + (f"; {row['host_reads_per_step']} host reads a step:" if row["host_reads_per_step"] is not None else ""))
    for place, n in row["places"].items():
        print(f"{n:5d}  {place}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
