"""GPU check: one preset on the Lego (known poses: no pycolmap, no network) on the device recon picks, measured.

    python benchmarks/gpu_check.py --out /tmp/gpu_check                 # ≤ 8 min on an H100/H200
    python benchmarks/gpu_check.py --out /tmp/gpu_check --set train.device_sizing=off --set train.compile=off
    python benchmarks/gpu_check.py --out /tmp/smoke --smoke              # minutes on a CPU: that it runs

Runs the real pipeline (poses imported from transforms_*.json, normalize, train, mesh) with the preset as
`recon run --preset` would, then prints one table and writes gpu_check.json (with the commit and machine, as every
record in benchmarks/results/): training steps and rays/s, held-out PSNR over the test views (all 200 unless
--test-views), render milliseconds per 400² view (timed after a warm-up, the device synchronized), the mesh stage's
seconds, and the CPU-vs-device agreement: the trained field rendered on the CPU and on the device for the same
views, as the PSNR of one render against the other (the CPU's C marcher against CUDA's torch path; 40 dB and up
means the two paths draw the same image). A check measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
LEGO_HALF = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_half"

SMOKE = ["train.budget=5s", "train.max_side=100", "train.eval_every=0", "mesh.max_resolution=64",
         "mesh.texture_faces=0"]
"""--smoke: a few seconds of training on 100-px photos and a 64³ mesh: that every part runs, not what it measures."""


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def render_timing(field: Path, views: list[Any], device: torch.device) -> float:
    """Milliseconds per view to render `views` on `device` (one warm-up render first: allocation, compilation)."""
    from recon.field import load_field
    from recon.views import render_view

    model, meta = load_field(field, device)
    aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=device) if meta.get("bounded") else None
    background = np.asarray(meta["background"], np.float32)
    render_view(model, views[0], aabb, background)
    _sync(device)
    t0 = time.perf_counter()
    for view in views:
        render_view(model, view, aabb, background)
    _sync(device)
    return 1000.0 * (time.perf_counter() - t0) / len(views)


def device_agreement(field: Path, views: list[Any], device: torch.device) -> dict[str, Any]:
    """The same trained field rendered on the CPU and on `device`: PSNR of one render against the other (min, mean)
    and the largest pixel difference; skipped when `device` is the CPU."""
    from recon.field import load_field
    from recon.metrics import psnr
    from recon.views import render_view

    if device.type == "cpu":
        return {"skipped": "the device is the CPU: nothing to compare with"}
    renders = {}
    for where in (torch.device("cpu"), device):
        model, meta = load_field(field, where)
        aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=where) if meta.get("bounded") else None
        renders[where.type] = [render_view(model, v, aabb, np.asarray(meta["background"], np.float32))["rgb"] for v in views]
    db = [float(psnr(torch.from_numpy(a), torch.from_numpy(b))) for a, b in zip(renders["cpu"], renders[device.type], strict=True)]
    diff = max(float(np.abs(a - b).max()) for a, b in zip(renders["cpu"], renders[device.type], strict=True))
    return {"views": len(views), "psnr_min_db": round(min(db), 2), "psnr_mean_db": round(float(np.mean(db)), 2),
            "max_abs_diff": round(diff, 4)}


def run_check(args: argparse.Namespace) -> dict[str, Any]:
    from recon.bench import provenance
    from recon.config import load_config
    from recon.nerf.device import select_device
    from recon.progress import Reporter
    from recon.scene import load_scene, spread_evenly
    from recon.stages import default_pipeline
    from recon.views import load_views

    overrides = [*(SMOKE if args.smoke else []), f"train.final_eval_views={args.test_views}", *args.set]
    if args.budget:
        overrides.append(f"train.budget={args.budget}")
    config = load_config(args.preset, overrides)
    device = select_device(config.train.device)
    scene = args.out / f"lego-{args.preset}"
    if scene.exists() and not args.keep:
        shutil.rmtree(scene)
    report = Reporter(quiet=args.quiet)
    t0 = time.perf_counter()
    outcomes = default_pipeline().run(scene, config, report, source=args.data.resolve(), preset=args.preset)
    wall = time.perf_counter() - t0
    metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
    stage_s = {o.name: round(o.wall_s, 1) for o in outcomes}
    normalized = load_scene(scene / "02_scene")
    tests = normalized.split("test") or normalized.split("val")
    timing_views = load_views(normalized, spread_evenly(tests, args.render_views + 1), config.train.max_side)
    agree_views = load_views(normalized, spread_evenly(tests, args.agreement_views), config.train.max_side)
    row = {
        "name": args.preset,
        "data": str(args.data),
        "overrides": overrides,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **provenance(),
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "sizing": config.train.adjusted,
        "steps": metrics["steps"],
        "batch_rays": config.train.batch_rays,
        "train_time_s": metrics["train_time_s"],
        "rays_per_s": metrics["rays_per_s"],
        "ms_per_step": round(1000.0 * metrics["train_time_s"] / max(1, metrics["steps"]), 2),
        "psnr": round(metrics["test"]["psnr"], 2),
        "ssim": round(metrics["test"]["ssim"], 4),
        "test_views": len(metrics["test"]["views"]),
        "render_ms_per_view": round(render_timing(scene / "03_field", timing_views[1:] or timing_views, device), 1),
        "render_size": list(timing_views[0].hw),
        "mesh_stage_s": stage_s.get("mesh"),
        "stage_wall_s": stage_s,
        "wall_s": round(wall, 1),
        "cpu_vs_device": device_agreement(scene / "03_field", agree_views, device),
        "reasons": metrics["reasons"],
    }
    return row


def table(row: dict[str, Any]) -> str:
    """The check's one table (Markdown)."""
    agree = row["cpu_vs_device"]
    agreement = (agree["skipped"] if "skipped" in agree else
                 f"{agree['psnr_min_db']:.1f} dB min / {agree['psnr_mean_db']:.1f} dB mean over {agree['views']} views")
    cells = [
        ("device", f"{row['device']} ({row['device_name']})"),
        ("preset", f"{row['name']}: {row['batch_rays']:,} rays/step"),
        ("steps", f"{row['steps']:,} in {row['train_time_s']:.0f} s ({row['ms_per_step']:.1f} ms/step)"),
        ("rays/s", f"{row['rays_per_s']:,.0f}"),
        ("test PSNR", f"{row['psnr']:.2f} dB, SSIM {row['ssim']:.3f} over {row['test_views']} views"),
        ("render", f"{row['render_ms_per_view']:.0f} ms per {row['render_size'][1]}×{row['render_size'][0]} view"),
        ("mesh stage", f"{row['mesh_stage_s']} s"),
        ("CPU vs device", agreement),
        ("wall", f"{row['wall_s']:.0f} s (all stages)"),
    ]
    return "\n".join(["| measure | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in cells)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the scene, gpu_check.json and gpu_check.md")
    parser.add_argument("--data", type=Path, default=LEGO_HALF, help="a NeRF-synthetic folder (default: the half-res Lego)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--budget", default="90s", help="training budget (the issue's runs: 90s); '' keeps the preset's")
    parser.add_argument("--test-views", type=int, default=0, help="held-out views scored (0: all)")
    parser.add_argument("--render-views", type=int, default=10, help="views timed for render ms/view")
    parser.add_argument("--agreement-views", type=int, default=3, help="views rendered on both the CPU and the device")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override, as recon --set")
    parser.add_argument("--smoke", action="store_true", help="tiny run (5 s budget, 100-px photos, 64³ mesh): that it runs")
    parser.add_argument("--keep", action="store_true", help="reuse the scene folder's cached stages")
    parser.add_argument("--quiet", action="store_true", help="only warnings and errors while the pipeline runs")
    args = parser.parse_args(argv)
    if not (args.data / "transforms_train.json").is_file():
        print(f"error: {args.data} has no transforms_train.json: pass --data with a NeRF-synthetic folder", file=sys.stderr)
        return 2
    if args.smoke:
        args.budget = ""
        args.test_views = args.test_views or 2
        args.render_views, args.agreement_views = min(args.render_views, 1), min(args.agreement_views, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    row = run_check(args)
    from recon.atomic import write_json_atomic

    write_json_atomic(args.out / "gpu_check.json", [row])
    text = table(row)
    (args.out / "gpu_check.md").write_text(f"# GPU check — {row['name']} on {args.data.name}\n\n{text}\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
