"""The mesh stage's parts at two (or more) checkouts, on one trained scene, the checkouts taking turns.

    python benchmarks/mesh_stage_turns.py --scene DIR --data PHOTOS --checkouts /tmp/old,. --rounds 3 \\
        [--preset fast] [--set mesh.cpu_bake_views=48 --set mesh.cpu_depth_side=400] --out FILE

A code change to the mesh stage is measured here, not an option (step_cost.py takes options in turns): each round
runs `recon run DATA --out SCENE --from mesh --until mesh --force` once from each checkout (its own recon on
PYTHONPATH), on the same trained field, and reads the stage's `timings_s` and the textured copy's from
`04_mesh/mesh_report.json`. A host that slows down slows every checkout alike. The record gives each checkout's commit,
its rounds and the median of each part over them, and the mesh each made (faces; the same field gives the same mesh
unless the change meant to change it): its pieces and the largest one's share of the area, the share of the photos'
object it covers and of the photos' SfM points it misses (`coherence`), and with `--gt-mesh` its accuracy against
that true surface (`recon eval --gt-mesh`, from the same checkout). A measurement: it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def run_mesh(checkout: Path, scene: Path, data: Path, preset: str, sets: list[str],
             gt_mesh: Path | None = None) -> dict[str, Any]:
    """One mesh stage from `checkout`; its report's timings, the textured copy's, the mesh's faces and shape, the
    stage's wall, and with `gt_mesh` its accuracy against it."""
    command = [sys.executable, "-m", "recon", "run", str(data), "--out", str(scene), "--preset", preset,
               "--from", "mesh", "--until", "mesh", "--force", "--quiet", *(a for s in sets for a in ("--set", s))]
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    t = time.perf_counter()
    done = subprocess.run(command, cwd=checkout, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise SystemExit(f"{checkout}: the mesh stage failed (exit {done.returncode}): {done.stderr[-1500:]}")
    report = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
    coherence = report.get("coherence") or {}
    shape = {"pieces": (coherence.get("largest_piece") or {}).get("pieces"),
             "largest_piece_area": (coherence.get("largest_piece") or {}).get("largest_area_fraction"),
             "object_covered": (coherence.get("projected") or {}).get("coverage"),
             "points_missed": (coherence.get("points") or {}).get("missing"),
             "components_removed": report.get("components_removed")}
    if gt_mesh is not None:
        out = scene / "eval_turns"
        command = [sys.executable, "-m", "recon", "eval", str(scene), "--gt-mesh", str(gt_mesh), "--out", str(out)]
        done = subprocess.run(command, cwd=checkout, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{checkout}: recon eval --gt-mesh failed (exit {done.returncode}): {done.stderr[-1500:]}")
        accuracy = json.loads((out / "mesh_accuracy.json").read_text())
        shape.update({key: accuracy[key] for key in ("fscore@0.01", "fscore@0.005", "chamfer_l1_rel",
                                                     "normal_consistency")})
    return {"timings_s": report["timings_s"], "texture_timings_s": (report.get("textured") or {}).get("timings_s"),
            "faces": report["faces"], "mesh": shape, "process_wall_s": round(wall, 2)}


def commit_of(checkout: Path) -> dict[str, Any]:
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(checkout), *args], capture_output=True, text=True).stdout.strip()
    return {"commit": git("rev-parse", "HEAD"), "uncommitted_changes": bool(git("status", "--porcelain", "--untracked-files=no"))}


def medians(rounds: list[dict[str, Any]], key: str) -> dict[str, float]:
    parts = [r[key] for r in rounds if r.get(key)]
    return {k: round(statistics.median(p[k] for p in parts), 3) for k in (parts[0] if parts else {})}


def main(argv: list[str] | None = None) -> int:
    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="a scene folder whose train stage is done")
    parser.add_argument("--data", type=Path, required=True, help="the photos (or poses) the scene was made from")
    parser.add_argument("--checkouts", required=True, help="comma-separated recon checkouts (worktrees), in turn order")
    parser.add_argument("--preset", default="fast", help="the preset the scene was trained with")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a mesh override, as recon --set")
    parser.add_argument("--gt-mesh", type=Path, help="the true surface, to score each mesh against (recon eval)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    checkouts = [Path(c).resolve() for c in args.checkouts.split(",") if c.strip()]
    missing = [str(c) for c in checkouts if not (c / "recon" / "__init__.py").exists()]
    if missing or not (args.scene / "03_field").is_dir() or args.rounds < 1:
        print(f"error: need recon checkouts ({', '.join(missing) or 'ok'}), a trained --scene ({args.scene}) and "
              f"--rounds >= 1", file=sys.stderr)
        return 2
    row: dict[str, Any] = {"name": "mesh_stage_turns", "scene": str(args.scene), "data": str(args.data),
                           "preset": args.preset, "overrides": args.set, "rounds": args.rounds,
                           "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **provenance(),
                           "load_average_start": [round(x, 2) for x in os.getloadavg()]}
    runs: dict[Path, list[dict[str, Any]]] = {c: [] for c in checkouts}
    for i in range(args.rounds):
        for checkout in checkouts:
            runs[checkout].append(run_mesh(checkout, args.scene, args.data, args.preset, args.set, args.gt_mesh))
            print(f"round {i + 1}, {checkout}: {runs[checkout][-1]['timings_s']['total_s']} s", flush=True)
    row["load_average_end"] = [round(x, 2) for x in os.getloadavg()]
    row["checkouts"] = [{"path": str(c), **commit_of(c), "median_timings_s": medians(runs[c], "timings_s"),
                         "median_texture_timings_s": medians(runs[c], "texture_timings_s"),
                         "faces": [r["faces"] for r in runs[c]], "mesh": runs[c][-1]["mesh"], "rounds": runs[c]}
                        for c in checkouts]
    write_json_atomic(args.out, [row])
    for c in row["checkouts"]:
        print(f"{c['commit'][:7]}: " + ", ".join(f"{k} {v}" for k, v in c["median_timings_s"].items()))
        print("    mesh: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                     for k, v in c["mesh"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
