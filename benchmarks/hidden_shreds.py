"""What dropping the hidden-face cut's shreds would do to a mesh: one trained field meshed twice, as shipped and with
the pieces that removing hidden faces leaves cut off from the surface dropped as floaters (under
`mesh.min_component_fraction` of the largest piece's area), each scored against the true surface.

    python benchmarks/hidden_shreds.py --scene SCENE --gt fixtures/sample/gt_mesh.ply --name sample_hidden_shreds

SCENE is a scene whose train stage is done (e.g. a `recon bench --data sample` preset folder); it is copied, not
changed. Writes benchmarks/results/<name>.json: per variant the mesh's pieces, F-scores, precision, recall,
Chamfer-L1 and normal agreement. It measures; it asserts nothing.
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
    parser.add_argument("--scene", type=Path, required=True, help="a scene with its field trained")
    parser.add_argument("--gt", type=Path, required=True, help="the true surface")
    parser.add_argument("--name", required=True, help="the record: benchmarks/results/<name>.json")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "recon" / "hidden_shreds")
    args = parser.parse_args()

    import recon.geometry.clean as clean
    from recon.app.bench import provenance
    from recon.app.cli import main as recon_cli
    from recon.atomic import write_json_atomic
    from recon.config import load_config
    from recon.evaluation.mesh_eval import compare_to_gt

    shipped = clean.remove_hidden_faces
    min_fraction = load_config().mesh.min_component_fraction

    def hidden_then_shreds(mesh: Any, seen_fn: Any) -> tuple[Any, dict]:
        mesh, report = shipped(mesh, seen_fn)
        mesh, shreds = clean.remove_small_components(mesh, min_fraction)
        return mesh, {**report, "shreds_removed": shreds["removed"], "shreds_area": shreds.get("removed_area", 0.0)}

    field = json.loads((args.scene / "03_field" / "metrics.json").read_text())
    rows: list[dict[str, Any]] = []
    for variant, remove_hidden in (("shipped", shipped), ("shreds dropped", hidden_then_shreds)):
        scene = args.work / variant.replace(" ", "_")
        if scene.exists():
            shutil.rmtree(scene)
        shutil.copytree(args.scene, scene, ignore=shutil.ignore_patterns(".lock", ".work", "04_mesh"))
        clean.remove_hidden_faces = remove_hidden
        date, load_start = datetime.now(timezone.utc).isoformat(timespec="seconds"), os.getloadavg()
        sys.argv = ["recon", "mesh", str(scene)]  # the mesh stage as a user runs it again, with the scene's config
        try:
            recon_cli()
        except SystemExit as done:
            if done.code:
                raise
        finally:
            clean.remove_hidden_faces = shipped
        report = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
        acc = compare_to_gt(scene, args.gt)
        rows.append({
            "variant": variant, "scene": str(args.scene), "field_steps": field.get("steps"), **provenance(),
            "date": date, "load_average_start": [round(x, 2) for x in load_start],
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
            "mesh_pieces": report["coherence"]["largest_piece"]["pieces"],
            "mesh_largest_piece_area": round(report["coherence"]["largest_piece"]["largest_area_fraction"], 5),
            "shreds_removed": report["clean"]["hidden"].get("shreds_removed", 0),
            **{key.replace("@", "_"): acc.get(key) for key in (
                "fscore@0.01", "precision@0.01", "recall@0.01", "fscore@0.005", "chamfer_l1_rel", "normal_consistency")},
        })
        print(rows[-1])
        write_json_atomic(REPO / "benchmarks" / "results" / f"{args.name}.json", rows)


if __name__ == "__main__":
    main()
