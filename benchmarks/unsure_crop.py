"""What the unsure automatic masks' crop does to a mesh: one field trained on the whole photos (normalize was not sure
enough of its automatic masks to train with them) meshed twice, with `mesh.unsure_masks=off` and `auto`, each scored
against the true surface.

    python benchmarks/unsure_crop.py --scene SCENE --gt CAPTURE/gt_mesh.ply --name unsure_crop --label LABEL

SCENE is a scene whose train stage is done and whose 02_scene holds masks_unsure/ (e.g. a `far_tabletop.py --table
plain --painted` run's scene); it is copied, not changed. Appends to benchmarks/results/<name>.json one row per
variant: the mesh's faces and pieces, F-scores, precision, recall and Chamfer-L1. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True, help="a scene with its field trained without masks")
    parser.add_argument("--gt", type=Path, required=True, help="the true surface (its transforms.json beside it)")
    parser.add_argument("--name", required=True, help="the record: benchmarks/results/<name>.json")
    parser.add_argument("--label", required=True, help="what the scene is, in the record")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "recon" / "unsure_crop")
    args = parser.parse_args()

    from recon.app.bench import provenance
    from recon.app.cli import main as recon_cli
    from recon.atomic import write_json_atomic
    from recon.evaluation.mesh_eval import compare_to_gt

    if not (args.scene / "02_scene" / "masks_unsure").is_dir():
        sys.exit(f"{args.scene} has no 02_scene/masks_unsure/: its automatic masks were trusted, or none were made")
    record = REPO / "benchmarks" / "results" / f"{args.name}.json"
    rows: list[dict[str, Any]] = json.loads(record.read_text()) if record.exists() else []
    field = json.loads((args.scene / "03_field" / "metrics.json").read_text())
    where = provenance()
    for variant in ("off", "auto"):
        scene = args.work / variant
        if scene.exists():
            shutil.rmtree(scene)
        shutil.copytree(args.scene, scene, ignore=shutil.ignore_patterns(".lock", ".work", "04_mesh", "eval"))
        date, load_start = datetime.now(timezone.utc).isoformat(timespec="seconds"), os.getloadavg()
        sys.argv = ["recon", "mesh", str(scene), "--set", f"mesh.unsure_masks={variant}"]
        try:
            recon_cli()
        except SystemExit as done:
            if done.code:
                raise
        report = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
        acc = compare_to_gt(scene, args.gt)
        rows.append({
            "label": args.label, "variant": f"mesh.unsure_masks={variant}", "scene": str(args.scene),
            "field_steps": field.get("steps"), **_trained(args.scene), **where, "date": date,
            "load_average_start": [round(x, 2) for x in load_start],
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
            "mesh_faces": report["faces"], "mesh_pieces": report["coherence"]["largest_piece"]["pieces"],
            "faces_outside_masks_removed": report["clean"].get("masked", {}).get("faces_removed", 0),
            **{key.replace("@", "_"): acc.get(key) for key in (
                "fscore@0.01", "precision@0.01", "recall@0.01", "fscore@0.005", "chamfer_l1_rel")},
        })
        print(rows[-1])
        write_json_atomic(record, rows)


def _trained(scene: Path) -> dict[str, Any]:
    """When the scene's field was trained, and by which version of the train stage (its manifest does not name the
    commit: the record's own commit is the mesh's)."""
    stage = json.loads((scene / "manifest.json").read_text()).get("stages", {}).get("train", {})
    return {"field_trained": stage.get("finished"), "field_train_version": stage.get("version")}


if __name__ == "__main__":
    main()
