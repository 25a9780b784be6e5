"""What one mesh option buys on fields already trained: each scene's mesh stage run once per value of the option, on
a copy of the scene (the same field every time, so the rows differ by the option alone, not by a training's noise).

    python benchmarks/mesh_options.py --option mesh.ground_margin_cells --values 2,-1 --name ground_margin \
        --scene painted=~/.cache/recon/bench/painted_view/tabletop_painted-fast \
        --gt painted=~/.cache/recon/datasets/tabletop_painted/capture/gt_mesh.ply

A scene is LABEL=DIR (a scene folder whose train stage is done, e.g. one a `recon bench` or option_sweep.py run
kept); --gt LABEL=PLY scores that scene's meshes against a true surface (aligned through the true poses beside it),
and without one the row holds what the mesh stage measures itself (pieces, coverage of the object's pixels, SfM
points it passes by). Writes benchmarks/results/<name>.json after each mesh. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def labelled(items: list[str], what: str) -> dict[str, Path]:
    """LABEL=PATH items -> {label: path}."""
    out = {}
    for item in items:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            sys.exit(f"{what} takes LABEL=PATH, got {item!r}")
        out[label] = Path(path).expanduser()
    return out


def mesh_row(scene: Path, gt: Path | None) -> dict[str, Any]:
    """The mesh stage's own checks, and the comparison with the true surface when there is one."""
    report = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
    coherence, clean = report.get("coherence", {}), report.get("clean", {})
    row: dict[str, Any] = {
        "faces": clean.get("output", {}).get("faces") or report.get("faces"),
        "ground_cut_faces": clean.get("ground_cut", {}).get("faces_removed"),
        "mesh_pieces": coherence.get("largest_piece", {}).get("pieces"),
        "mesh_coverage": (coherence.get("projected") or {}).get("coverage"),
        "mesh_points_missing": (coherence.get("points") or {}).get("missing"),
        "watertight": report.get("watertight"),
        "area": clean.get("output", {}).get("area"),
    }
    if row["watertight"]:  # the solid's volume, scene units³ (normalized frame)
        import trimesh

        row["volume"] = float(trimesh.load(scene / "04_mesh" / "mesh.ply", process=False).volume)
    if gt is not None:
        from recon.evaluation.mesh_eval import compare_to_gt

        acc = compare_to_gt(scene, gt)
        row.update({"fscore_1pct": acc["fscore@0.01"], "fscore_05pct": acc["fscore@0.005"],
                    "precision_05pct": acc["precision@0.005"], "recall_05pct": acc["recall@0.005"],
                    "precision_1pct": acc["precision@0.01"], "recall_1pct": acc["recall@0.01"],
                    "chamfer_rel": acc["chamfer_l1_rel"], "normal_consistency": acc.get("normal_consistency"),
                    "volume_ratio": acc.get("volume_ratio")})
    return row


def fresh_copy(source: Path, scene: Path, *stale: str) -> None:
    """Copy the scene folder `source` to `scene` (replacing what is there), without its lock, its work folder and the
    stage folders in `stale`, which the run redoes."""
    if scene.exists():
        shutil.rmtree(scene)
    shutil.copytree(source, scene, ignore=shutil.ignore_patterns(".lock", ".work", *stale))


def add_retrain_options(parser: argparse.ArgumentParser) -> None:
    """The options of a script that trains and meshes copies of one normalized scene: the scene, its true surface,
    overrides for every run, the record's name and the scratch folder."""
    parser.add_argument("--scene", type=Path, required=True, help="a scene folder whose normalize stage is done")
    parser.add_argument("--gt", type=Path, default=None, help="the true surface (PLY), for the mesh's accuracy")
    parser.add_argument("--set", action="append", default=[], help="overrides for every run")
    parser.add_argument("--name", required=True, help="the record: benchmarks/results/<name>.json")
    parser.add_argument("--work", type=Path, default=None, help="scratch (default: ~/.cache/recon/bench/<name>)")


def retrain_setup(args: argparse.Namespace) -> tuple[Path, Path, Path, str | None, dict[str, str]]:
    """From add_retrain_options' options: (the scene, the record's path, the scratch folder, the scene's preset, the
    overrides as a dict)."""
    source = args.scene.expanduser()
    result = REPO / "benchmarks" / "results" / f"{args.name}.json"
    work = args.work or Path.home() / ".cache" / "recon" / "bench" / args.name
    return source, result, work, recorded_preset(source), dict(item.split("=", 1) for item in args.set)


def recorded_preset(scene: Path) -> str | None:
    """The preset the scene was made with (its manifest's)."""
    return json.loads((scene / "manifest.json").read_text()).get("preset")


def run_stages(scene: Path, preset: str | None, overrides: dict[str, str], from_stage: str) -> dict[str, Any]:
    """Run the scene's stages from `from_stage` through the mesh, forced; the fields every record's row carries (when,
    on which commit and machine, under what load)."""
    from recon.app.api import run
    from recon.app.bench import load_average, provenance

    load_start, date = load_average(), datetime.now(timezone.utc).isoformat(timespec="seconds")
    run(None, scene, preset, overrides, from_stage=from_stage, until_stage="mesh", force=True)
    return {"date": date, **provenance(), "load_average_start": load_start}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--option", required=True, help="a mesh.* --set key, e.g. mesh.ground_margin_cells")
    parser.add_argument("--values", required=True, help="comma-separated values, run in this order")
    parser.add_argument("--scene", action="append", required=True, help="LABEL=DIR, a trained scene (repeatable)")
    parser.add_argument("--gt", action="append", default=[], help="LABEL=PLY, the true surface of that scene")
    parser.add_argument("--set", action="append", default=[], help="more mesh.* overrides, the same for every value")
    parser.add_argument("--name", required=True, help="the record: benchmarks/results/<name>.json")
    parser.add_argument("--work", type=Path, default=None,
                        help="where the scenes are copied (default: ~/.cache/recon/bench/<name>)")
    args = parser.parse_args()
    if not args.option.startswith("mesh."):
        sys.exit("--option must be a mesh.* option: the fields are reused, only the mesh stage runs again")

    from recon.atomic import write_json_atomic

    scenes, truths = labelled(args.scene, "--scene"), labelled(args.gt, "--gt")
    result = REPO / "benchmarks" / "results" / f"{args.name}.json"
    work = args.work or Path.home() / ".cache" / "recon" / "bench" / args.name
    rows: list[dict[str, Any]] = []
    for label, original in scenes.items():
        scene = work / label
        if scene.resolve() == original.resolve() or scene.resolve() in original.resolve().parents:
            sys.exit(f"--scene {label}={original} lies in the work folder {work}: give --work another folder")
        fresh_copy(original, scene, "04_mesh")
        preset = recorded_preset(scene)
        for value in args.values.split(","):
            overrides = dict(item.split("=", 1) for item in [*args.set, f"{args.option}={value}"])
            ran = run_stages(scene, preset, overrides, "mesh")
            row = {"scene": label, "source_scene": str(original), "preset": preset, "option": args.option,
                   "value": value, "overrides": args.set, **ran, **mesh_row(scene, truths.get(label))}
            rows.append(row)
            f = f", F@0.5% {row['fscore_05pct']:.3f}" if "fscore_05pct" in row else ""
            print(f"{label} {args.option}={value}: {row['mesh_pieces']} piece(s), coverage {row['mesh_coverage']}{f}")
            write_json_atomic(result, rows)
    print(f"wrote {result}")


if __name__ == "__main__":
    main()
