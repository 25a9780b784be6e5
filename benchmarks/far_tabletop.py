"""A small object on a table photographed from further back, without masks: what recon makes of it.

    python benchmarks/far_tabletop.py --work /tmp/far_tabletop --name far_tabletop --label shipped [--set KEY=VALUE]

Renders `python fixtures/gen_tabletop.py --realistic --far --views 24 --size 640x480` into WORK/capture (cached: the
object spans about 30% of each photo, the table, its clutter and the room the rest), copies its photos alone into
WORK/images (no masks), runs `recon run WORK/images --out WORK/scene-LABEL --preset fast` for a fixed 4,000 steps with
any `--set` given, then `recon eval --gt-mesh` against the object's true surface. Appends a row (label, overrides,
normalize's object region and masks as it said them, the training size's reason, steps, rays/s, held-out PSNR, mesh
faces, precision and recall at 1%, F@1%, F@0.5%, Chamfer, commit and machine) to benchmarks/results/NAME.json. It
measures; it asserts nothing.

    python benchmarks/far_tabletop.py --work /tmp/far_tabletop --figure docs/far_tabletop.png --labels A B

draws the first photo and the meshes of the runs labelled A and B (earlier runs' scenes in --work) in a row.
`--arc DEG` measures another capture the same way: the realistic tabletop at the usual distance, its photos within
an arc of DEG degrees (`gen_tabletop.py --realistic --arc DEG`: the object's front only), in place of the far one.
`--object NAME` does so with another object on the table (`gen_tabletop.py --realistic --object NAME`: a thin rod
and plate, a bowl, a ring on a drilled block, three separate pieces), photographed all round at the usual distance
(or within `--arc`); `--table plain` with a plain white table top (`gen_tabletop.py --realistic --table plain`),
which gives SfM next to nothing to match beside the object; `--painted` with the object painted in a few flat colours
(few features on it); `--dark` with the object dark. `--poses-from LABEL` starts from the SfM poses of the earlier run
labelled LABEL (SfM differs from run to run). `--views N` takes N photos instead of 24.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "fixtures"))


def main() -> None:
    from blurred_photos import run_fast, sample_run_parser, scene_of
    from gen_tabletop import generate
    from mixed_orientation import append_row
    from recon.app.bench import provenance

    parser = sample_run_parser(__doc__, required=False)
    parser.add_argument("--figure", type=Path, default=None, help="only draw a photo and the meshes of --labels (an "
                        "earlier run's scenes in --work) into this PNG")
    parser.add_argument("--labels", nargs="+", default=[], help="the runs whose meshes --figure draws")
    parser.add_argument("--arc", type=float, default=None, help="the capture from an arc this many degrees wide at the "
                        "usual distance instead of from further back")
    parser.add_argument("--object", default=None, help="another object on the table (thin, concave, hole, pieces), at "
                        "the usual distance instead of from further back")
    parser.add_argument("--table", default=None, choices=("plain",), help="a plain white table top, at the usual "
                        "distance instead of from further back")
    parser.add_argument("--painted", action="store_true", help="the object painted in a few flat colours, at the "
                        "usual distance instead of from further back")
    parser.add_argument("--dark", action="store_true", help="the object dark, at the usual distance instead of "
                        "from further back")
    parser.add_argument("--views", type=int, default=24, help="how many photos (default 24)")
    parser.add_argument("--poses-from", default=None, help="the label of an earlier run in --work whose SfM poses "
                        "this run starts from (SfM differs from run to run)")
    args = parser.parse_args()
    if args.figure is not None:
        from closeups_share import tiles_row

        meshes = [scene_of(args.work, label) / "04_mesh" / "preview_front.png" for label in args.labels]
        return tiles_row([args.work / "images" / "view_000.jpg", *meshes], args.figure)
    if not (args.name and args.label):
        parser.error("--name and --label are needed to run (or --figure to draw)")
    where, load = provenance(), [round(x, 2) for x in os.getloadavg()]
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    no_variant = args.arc is None and args.object is None and args.table is None and not (args.painted or args.dark)
    shape = ({"far": True} if no_variant else
             {**({"arc": args.arc} if args.arc is not None else {}),
              **({"shape": args.object} if args.object is not None else {}),
              **({"table": args.table} if args.table is not None else {}),
              **({"painted": True} if args.painted else {}),
              **({"dark": True} if args.dark else {})})
    capture = generate(args.work / "capture", views=args.views, size="640x480", realistic=True, **shape)
    shutil.rmtree(args.work / "images", ignore_errors=True)
    shutil.copytree(capture / "images", args.work / "images")
    scene = scene_of(args.work, args.label)
    poses_from = scene_of(args.work, args.poses_from) if args.poses_from is not None else None
    metrics, accuracy = run_fast(args.work / "images", scene, args.overrides, truth=capture / "gt_mesh.ply",
                                 poses_from=poses_from)
    notes = json.loads((scene / "02_scene" / "scene.json").read_text())["notes"]
    mesh = json.loads((scene / "manifest.json").read_text())["stages"]["mesh"]["summary"]
    row = {"label": args.label, "overrides": args.overrides, "poses_from": args.poses_from, "views": args.views,
           "capture_shape": shape,
           "capture": notes.get("capture"),
           "region": notes.get("region"),
           "masks": notes.get("masks"),
           "training_size": next((r for r in metrics["reasons"] if r.startswith("training size")), None),
           "steps": metrics.get("steps"), "rays_per_s": metrics.get("rays_per_s"), "psnr": metrics["test"]["psnr"],
           "mesh_faces": mesh.get("faces"), "precision_1pct": accuracy.get("precision@0.01"),
           "recall_1pct": accuracy.get("recall@0.01"), "fscore_1pct": accuracy.get("fscore@0.01"),
           "fscore_05pct": accuracy.get("fscore@0.005"), "chamfer_rel": accuracy.get("chamfer_l1_rel"), **where,
           "date": date, "load_average_start": load, "load_average_end": [round(x, 2) for x in os.getloadavg()]}
    append_row(args.name, row)


if __name__ == "__main__":
    main()
