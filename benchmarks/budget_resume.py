"""What a longer --budget after a shorter one buys: one normalized scene trained and meshed under the long budget from
the start; under the short budget stopped partway (SIGINT, as a user who read the short-budget warning does) and then
run again with the long budget, which trains on from the stopped run's checkpoint; and under the short budget to the
end (its mesh made) and then run again with the long budget, which trains the finished field on. With --long-preset
the long runs take that preset (`balanced` after `fast`: the same field, a longer budget and a finer mesh).

    python benchmarks/budget_resume.py --scene ~/.cache/recon/bench/fox/fox-fast --short 4m --stop-after 150 \
        --long 8m --name fox_budget_resume
    python benchmarks/budget_resume.py --scene scene --short 4m --long 10m --long-preset balanced \
        --rows short_finished_then_long,long_from_the_start --gt fixtures/sample/gt_mesh.ply \
        --name sample_fast_then_balanced

The scene is copied once a row under the work folder (its poses and normalize stages as they are). Each row holds the
steps, training seconds and wall seconds (the continued rows' include the first run's), held-out PSNR and the mesh
stage's checks (against the true surface with --gt); the finished-first row also the short run's. Writes
benchmarks/results/<name>.json after each row. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))

STOPPED_RUN = """
import signal
import sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C's, even where a background job ignores SIGINT
from pathlib import Path
sys.path.insert(0, {repo!r})
from recon.app.api import run
run(None, Path({scene!r}), {preset!r}, {overrides!r}, from_stage="train", until_stage="mesh", force=True)
"""


def stop_training(scene: Path, preset: str | None, overrides: dict[str, str], after_s: float,
                  log: Path) -> dict[str, Any]:
    """Run the train stage in a child process and send it SIGINT (Ctrl-C) `after_s` seconds after it started; what
    the checkpoint it leaves holds (its training seconds: the start's loading and planning are not among them)."""
    code = STOPPED_RUN.format(repo=str(REPO), scene=str(scene), preset=preset, overrides=overrides)
    t0 = time.perf_counter()
    with log.open("w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=err, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=after_s)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
        proc.wait(timeout=600)
    wall = time.perf_counter() - t0
    found = sorted((scene / ".work").glob("train-*/checkpoint.pt"))
    if not found:
        sys.exit(f"the stopped run left no checkpoint (exit {proc.returncode}; its output: {log})")
    ckpt = torch.load(found[0], weights_only=False, map_location="cpu")
    return {"stopped_wall_s": round(wall, 1), "stopped_at_step": int(ckpt["state"]["step"]),
            "stopped_train_time_s": round(float(ckpt["train_time_s"]), 1)}


def _field_row(scene: Path) -> dict[str, Any]:
    metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
    return {"steps": metrics["steps"], "train_time_s": metrics["train_time_s"], "rays_per_s": metrics["rays_per_s"],
            "psnr": metrics["test"]["psnr"]}


def main() -> None:
    from mesh_options import add_retrain_options, fresh_copy, mesh_row, retrain_setup, run_stages

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", required=True, help="the budget of the first run (stopped or finished), e.g. 4m")
    parser.add_argument("--stop-after", type=float, default=0.0,
                        help="seconds after the stopped run starts at which it gets SIGINT (short_stopped_then_long)")
    parser.add_argument("--long", required=True, help="the longer budget, e.g. 8m")
    parser.add_argument("--long-preset", default=None,
                        help="the preset of the long runs (default: the scene's), e.g. balanced after a fast scene")
    parser.add_argument("--rows", default="long_from_the_start,short_stopped_then_long,short_finished_then_long",
                        help="which runs, comma-separated (all three by default)")
    add_retrain_options(parser)
    args = parser.parse_args()

    from recon.atomic import write_json_atomic

    source, result, work, preset, overrides = retrain_setup(args)
    long_preset = args.long_preset or preset
    rows: list[dict[str, Any]] = []
    gt = args.gt.expanduser() if args.gt else None
    for how in args.rows.split(","):
        if how not in ("long_from_the_start", "short_stopped_then_long", "short_finished_then_long"):
            sys.exit(f"--rows: no run called {how!r}")
        if how == "short_stopped_then_long" and args.stop_after <= 0:
            sys.exit("--rows short_stopped_then_long needs --stop-after SECONDS")
        scene = work / how
        fresh_copy(source, scene, "03_field", "04_mesh")
        first: dict[str, Any] = {}
        if how == "short_stopped_then_long":
            first = stop_training(scene, preset, {**overrides, "train.budget": args.short}, args.stop_after,
                                  work / f"{how}.log")
        elif how == "short_finished_then_long":
            t0 = time.perf_counter()
            run_stages(scene, preset, {**overrides, "train.budget": args.short}, "train")
            first = {"first_wall_s": round(time.perf_counter() - t0, 1),
                     **{f"short_{k}": v for k, v in _field_row(scene).items()},
                     **{f"short_{k}": v for k, v in mesh_row(scene, gt).items()}}
        t0 = time.perf_counter()
        ran = run_stages(scene, long_preset, {**overrides, "train.budget": args.long}, "train")
        wall = time.perf_counter() - t0 + first.get("stopped_wall_s", first.get("first_wall_s", 0.0))
        row = {"how": how, "short": args.short if first else None, "long": args.long, "source_scene": str(source),
               "preset": preset if first else long_preset, "long_preset": long_preset, "overrides": args.set, **ran,
               **first, "wall_s": round(wall, 1),
               **_field_row(scene), **mesh_row(scene, gt)}
        rows.append(row)
        print(f"{how}: {row['steps']} steps, {row['train_time_s']:.0f} s trained, {row['wall_s']:.0f} s in all, "
              f"PSNR {row['psnr']:.2f} dB, mesh coverage {row['mesh_coverage']}", flush=True)
        write_json_atomic(result, rows)
    print(f"record: {result}")


if __name__ == "__main__":
    main()
