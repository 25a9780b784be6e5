"""How many photos the mesh stage should check and colour the mesh against: its seconds and the mesh's held-out PSNR
for each count, on one trained field.

    python benchmarks/bake_views.py [--views 24:200,48:400,100:400] [--budget 60s] [--work DIR]

Trains the fast preset on the half-resolution Lego (known poses) for ``--budget`` once, then runs the mesh stage on
that field once per ``VIEWS:SIDE`` pair, with mesh.cpu_bake_views=VIEWS and mesh.cpu_depth_side=SIDE (the field's
depth maps rendered at most SIDE pixels; 400 is the Lego's training size, what a GPU renders them at). On a GPU the
depth maps are fast and what grows with the photos is the CPU's work: rasterizing the mesh into each photo, baking
its pixels into vertex colours and texels (the mesh stage's color_s and texture_s). Each row gives the stage's parts
(seconds) and the held-out PSNR of the meshes rendered into 8 test views (vertex colours, textured; over the
whole view and over the pixels both meshes cover). Writes benchmarks/results/bake_views.json. It measures; it
asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_check import LEGO_HALF, REPO, not_nerf_synthetic  # gpu_check puts this checkout's recon first

RESULT = REPO / "benchmarks" / "results" / "bake_views.json"


def mesh_row(scene: Path, data: Path, budget: str, views: int, side: int, where: dict[str, Any]) -> dict[str, Any]:
    """The pipeline on `scene` up to the mesh stage with these bake settings (poses, normalize, train cached);
    `where`: the run's provenance, read once before the first row (the record it rewrites is a tracked file)."""
    from recon.app.progress import Reporter
    from recon.config import load_config
    from recon.stages import default_pipeline

    overrides = [f"train.budget={budget}", "train.appearance=off", "train.device=cpu",
                 f"mesh.cpu_bake_views={views}", f"mesh.cpu_depth_side={side}"]
    config = load_config("fast", overrides)
    load = [round(x, 2) for x in os.getloadavg()]
    started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    outcomes = default_pipeline().run(scene, config, Reporter(quiet=True), source=data.resolve(), preset="fast")
    metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
    report = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
    held = report["textured"]["held_out"]
    return {
        "name": f"{views} views at {side} px",
        "date": started, **where, "load_average_start": load, "device": "cpu",
        "overrides": overrides,
        "steps": metrics["steps"], "rays_per_s": metrics["rays_per_s"], "psnr": round(metrics["test"]["psnr"], 2),
        "bake_views": report["colors"]["views"],
        "mesh_stage_s": next(round(o.wall_s, 1) for o in outcomes if o.name == "mesh"),
        "mesh_timings_s": report["timings_s"],
        "texture_timings_s": report["textured"]["timings_s"],
        "faces": report["faces"],
        "held_out_views": len(held["views"]),
        "held_out_psnr": {k: held[k] for k in ("psnr_vertex_colors", "psnr_textured", "psnr_vertex_colors_covered",
                                              "psnr_textured_covered")},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", default="24:200,48:400,100:400", help="VIEWS:SIDE pairs, comma-separated")
    parser.add_argument("--budget", default="60s", help="the field's training budget (trained once)")
    parser.add_argument("--data", type=Path, default=LEGO_HALF, help="a NeRF-synthetic folder (default: the half-res Lego)")
    parser.add_argument("--work", type=Path, default=None, help="scene folder (default: a new temporary one)")
    parser.add_argument("--out", type=Path, default=RESULT, help="the record to write")
    args = parser.parse_args(argv)
    try:
        pairs = [tuple(int(x) for x in p.split(":")) for p in args.views.split(",") if p.strip()]
    except ValueError:
        pairs = []
    error = not_nerf_synthetic(args.data)
    if not pairs or any(len(p) != 2 or min(p) < 1 for p in pairs):
        error = f"error: --views takes VIEWS:SIDE pairs of whole numbers (e.g. 24:200,48:400), got {args.views!r}"
    if error:
        print(error, file=sys.stderr)
        return 2
    scene = (args.work or Path(tempfile.mkdtemp(prefix="bake_views_"))) / "lego"
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic

    where = provenance()
    rows = []
    for views, side in pairs:
        rows.append(mesh_row(scene, args.data, args.budget, views, side, where))
        write_json_atomic(args.out, rows)
        r = rows[-1]
        t, h = r["mesh_timings_s"], r["held_out_psnr"]
        print(f"{r['name']}: mesh stage {r['mesh_stage_s']} s (depth maps {t.get('depth_s')}, colours {t['color_s']}, "
              f"texture {t.get('texture_s')}); held-out vertex colours {h['psnr_vertex_colors']:.2f} dB "
              f"({h['psnr_vertex_colors_covered']:.2f} where both cover), textured {h['psnr_textured']:.2f} dB "
              f"({h['psnr_textured_covered']:.2f})")
    print(f"record: {args.out} (scene in {scene})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
