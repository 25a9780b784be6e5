"""A small object in wide photos: what training at the preset's size costs its mesh, and what the larger size the
train stage picks (`train.small_object`) gains.

    python benchmarks/small_object.py --work /tmp/small --name small_object --label shipped [--set KEY=VALUE]

Pastes each of the shipped sample's 40 photos into the middle of a white canvas 3 times its size (the same cameras
with a lens three times wider: the object's box spans about 150 px of a 400-px photo instead of 430) in WORK/images,
runs `recon run WORK/images --out WORK/scene-LABEL --preset fast` for a fixed 4,000 steps (not the time budget: the
steps must not depend on the machine's load) with any `--set` given, then `recon eval --gt-mesh` against the sample's
true surface. Appends a row (label, overrides, the training size's reason, steps, rays/s, training seconds, held-out
PSNR and SSIM, mesh faces, F@1%, F@0.5%, Chamfer, the share of the true surface missed at 1% that lies on the object's
flat base, commit and machine) to benchmarks/results/NAME.json. It measures; it asserts nothing.

    python benchmarks/small_object.py --work /tmp/small --figure docs/small_object.png

draws a photo of the capture and the meshes of the runs labelled `train.small_object=off` and `shipped`.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from datetime import datetime, timezone
from pathlib import Path

from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))
SAMPLE = REPO / "fixtures" / "sample"
WIDER = 3
"""The canvas's size over the photo's: the object spans a third of the frame it spanned."""


def make_capture(images: Path) -> None:
    shutil.rmtree(images, ignore_errors=True)
    images.mkdir(parents=True)
    for path in sorted((SAMPLE / "images").iterdir()):
        photo = Image.open(path).convert("RGB")
        canvas = Image.new("RGB", (WIDER * photo.width, WIDER * photo.height), (255, 255, 255))
        canvas.paste(photo, ((WIDER - 1) * photo.width // 2, (WIDER - 1) * photo.height // 2))
        canvas.save(images / path.name, quality=92)


def missed_on_base(scene: Path, tolerance: float = 0.01, samples: int = 100_000) -> float | None:
    """The share of the true surface's points missed at `tolerance` of its diagonal that lie on its flat base (within
    0.5% of the diagonal of its lowest point): where the photos only graze it. None when none is missed."""
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree

    from recon.evaluation.mesh_eval import in_truth_frame

    ours, truth, *_ = in_truth_frame(scene, SAMPLE / "gt_mesh.ply")
    points, _ = trimesh.sample.sample_surface(truth, samples, seed=0)
    near, _ = trimesh.sample.sample_surface(ours, 4 * samples, seed=0)
    diagonal = float(np.linalg.norm(truth.bounds[1] - truth.bounds[0]))
    missed = cKDTree(near).query(points)[0] > tolerance * diagonal
    if not missed.any():
        return None
    return float(np.mean(points[missed, 2] <= truth.bounds[0, 2] + 0.005 * diagonal))


def figure(work: Path, out: Path) -> None:
    """A photo of the capture, then the mesh trained at the preset's side and at the side picked, in a row."""
    from blurred_photos import scene_of
    from closeups_share import tiles_row

    labels = ("train.small_object=off", "shipped")
    meshes = [scene_of(work, label) / "04_mesh" / "preview_front.png" for label in labels]
    tiles_row([work / "images" / "view_000.jpg", *meshes], out)


def main() -> None:
    from blurred_photos import run_fast, sample_run_parser, scene_of
    from mixed_orientation import append_row

    parser = sample_run_parser(__doc__, required=False)
    parser.add_argument("--figure", type=Path, default=None, help="only draw a photo and the meshes of the labels "
                        "train.small_object=off and shipped (an earlier run's scenes in --work) into this PNG")
    args = parser.parse_args()
    if args.figure is not None:
        return figure(args.work, args.figure)
    if not (args.name and args.label):
        parser.error("--name and --label are needed to run (or --figure to draw)")
    from recon.app.bench import provenance

    where, load = provenance(), [round(x, 2) for x in os.getloadavg()]
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    if not (args.work / "images").is_dir():
        make_capture(args.work / "images")
    scene = scene_of(args.work, args.label)
    metrics, accuracy = run_fast(args.work / "images", scene, args.overrides)
    mesh = json.loads((scene / "manifest.json").read_text())["stages"]["mesh"]["summary"]
    row = {"label": args.label, "overrides": args.overrides,
           "training_size": next((r for r in metrics["reasons"] if r.startswith("training size")), None),
           "steps": metrics.get("steps"), "rays_per_s": metrics.get("rays_per_s"),
           "train_time_s": metrics.get("train_time_s"), "psnr": metrics["test"]["psnr"],
           "ssim": metrics["test"]["ssim"], "mesh_faces": mesh.get("faces"),
           "fscore_1pct": accuracy.get("fscore@0.01"), "fscore_05pct": accuracy.get("fscore@0.005"),
           "chamfer_rel": accuracy.get("chamfer_l1_rel"), "missed_1pct_on_base": missed_on_base(scene), **where,
           "date": date, "load_average_start": load, "load_average_end": [round(x, 2) for x in os.getloadavg()]}
    append_row(args.name, row)


if __name__ == "__main__":
    main()
