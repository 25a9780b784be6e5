"""Photos taken upright and sideways in one capture: how well the poses stage places them, against reference poses.

    python benchmarks/mixed_orientation.py --work /tmp/mixed --name mixed_orientation_fox --label shipped [--every 3]

Copies the fox's 67 photos (1080×1920, no EXIF) into WORK/photos, every `--every`-th of them (by name; 0: none)
turned a quarter counterclockwise as a phone held sideways takes it (1920×1080, the camera rolled 90° about its
axis), runs `recon run WORK/photos --out WORK/scene --until poses` with this checkout's recon, and scores the cameras
against the fox's reference poses (each turned photo's pose rolled the same way): median and worst centre error over
the rig's radius and median rotation error after a robust similarity fit (`sfm_mapping.pose_scores`), and the focal
lengths against the reference one (median and worst relative error). Appends a row (the label, the photos registered,
COLMAP cameras, reprojection error, seconds, the scores, commit and machine) to benchmarks/results/NAME.json. It
measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))
FOX = REPO.parent / "shared" / "data" / "fox"
ROLL = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""A photo turned a quarter counterclockwise is taken by the camera rolled by this (OpenGL camera-to-world, right)."""


def make_capture(photos: Path, every: int) -> set[str]:
    """The fox's photos in `photos`, every `every`-th turned; the names of those turned."""
    if photos.exists():
        shutil.rmtree(photos)
    photos.mkdir(parents=True)
    turned = set()
    for i, path in enumerate(sorted((FOX / "images").iterdir())):
        if every and i % every == 0:
            with Image.open(path) as img:
                img.transpose(Image.Transpose.ROTATE_90).save(photos / path.name, quality=95)
            turned.add(path.stem)
        else:
            shutil.copyfile(path, photos / path.name)
    return turned


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--name", required=True)
    parser.add_argument("--label", required=True, help="what this row measures (e.g. shipped, before)")
    parser.add_argument("--every", type=int, default=3, help="turn every N-th photo (0: none)")
    args = parser.parse_args()
    from recon.app.bench import provenance
    from sfm_mapping import pose_scores

    where = provenance()
    load = [round(x, 2) for x in os.getloadavg()]
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    turned = make_capture(args.work / "photos", args.every)
    scene = args.work / "scene"
    shutil.rmtree(scene, ignore_errors=True)
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "recon", "run", str(args.work / "photos"), "--out", str(scene),
                          "--until", "poses", "--preset", "fast", "-q"], cwd=REPO, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    seconds = time.perf_counter() - start
    row = {"label": args.label, "turned": len(turned), "photos": 67, "exit": run.returncode,
           "seconds": round(seconds, 1)}
    if run.returncode == 0:
        summary = json.loads((scene / "manifest.json").read_text())["stages"]["poses"]["summary"]
        doc = json.loads((FOX / "transforms.json").read_text())
        truth = {}
        for f in doc["frames"]:
            c2w = np.asarray(f["transform_matrix"], float)
            if Path(f["file_path"]).stem in turned:
                c2w[:3, :3] = c2w[:3, :3] @ ROLL
            truth[Path(f["file_path"]).stem] = c2w
        shared = json.loads((scene / "01_poses" / "scene.json").read_text())
        frames = {Path(f["file_path"]).name: f for f in shared["frames"]}
        focal = np.array([(f.get("fl_x", shared.get("fl_x")) + f.get("fl_y", shared.get("fl_y"))) / 2
                          for f in frames.values()])
        focal_ref = (doc["fl_x"] + doc["fl_y"]) / 2
        focal_err = np.abs(focal - focal_ref) / focal_ref
        row.update({"registered": summary["registered"], "cameras": summary["cameras"],
                    "reprojection_error_px": summary["reprojection_error_px"],
                    "camera_choice": shared["notes"].get("camera_choice"),
                    **pose_scores({n: {"c2w": f["transform_matrix"]} for n, f in frames.items()}, truth),
                    "turned_rotation_error_median_deg": pose_scores(
                        {n: {"c2w": f["transform_matrix"]} for n, f in frames.items() if Path(n).stem in turned},
                        truth)["rotation_error_median_deg"] if turned else None,
                    "focal_error_median": float(np.median(focal_err)), "focal_error_max": float(focal_err.max())})
    else:
        row["error"] = (run.stdout + run.stderr)[-2000:]
    row.update({**where, "date": date, "load_average_start": load})
    append_row(args.name, row)


def append_row(name: str, row: dict) -> None:
    """One more row in benchmarks/results/NAME.json (a list of rows), shown."""
    out = REPO / "benchmarks" / "results" / f"{name}.json"
    rows = json.loads(out.read_text()) if out.is_file() else []
    rows.append(row)
    out.write_text(json.dumps(rows, indent=1) + "\n")
    print(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
