"""A few shaken photos among sharp ones: what they cost the field and the mesh, and what leaving them out gains.

    python benchmarks/blurred_photos.py --work /tmp/blurred --name blurred_photos --label shipped [--set KEY=VALUE]

Copies the shipped sample's 40 photos into WORK/images with four training photos (view_003, _013, _021, _029: none of
the held-out ones) smeared by a straight camera shake of 2% of the photo's width in a direction of its own, runs
`recon run WORK/images --out WORK/scene-LABEL --preset fast` for a fixed 4,000 steps (not the time budget: the steps
must not depend on the machine's load) with any `--set` given, then `recon eval --gt-mesh` against the sample's true
surface. Appends a row (label, overrides, which photos normalize left out and why, steps, rays/s, held-out PSNR and
SSIM, F@1%, F@0.5%, Chamfer, commit and machine) to benchmarks/results/NAME.json. It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))
SAMPLE = REPO / "fixtures" / "sample"
SHAKEN = {"view_003.jpg": 20.0, "view_013.jpg": 75.0, "view_021.jpg": 140.0, "view_029.jpg": 300.0}
"""The photos shaken, with the direction of each shake in degrees."""
SHAKE = 0.02
"""The shake's length, as a share of the photo's width."""


def shaken(image: np.ndarray, degrees: float, length: float) -> np.ndarray:
    """`image` smeared along a straight line of `length` pixels at `degrees` (a hand's shake during the exposure)."""
    size = int(np.ceil(length)) | 1
    kernel = np.zeros((size, size), np.float32)
    c, d = size // 2, np.radians(degrees)
    for t in np.linspace(-length / 2, length / 2, 4 * size):
        kernel[int(round(c + t * np.sin(d))), int(round(c + t * np.cos(d)))] += 1.0
    return cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def make_capture(images: Path, shake: float) -> None:
    shutil.rmtree(images, ignore_errors=True)
    images.mkdir(parents=True)
    for path in sorted((SAMPLE / "images").iterdir()):
        if path.name in SHAKEN and shake > 0:
            photo = cv2.imread(str(path))
            cv2.imwrite(str(images / path.name), shaken(photo, SHAKEN[path.name], shake * photo.shape[1]),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
        else:
            shutil.copyfile(path, images / path.name)


def recon(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "recon", *args], cwd=REPO, check=True,
                   env={**os.environ, "PYTHONPATH": str(REPO)})


def run_fast(images: Path, scene: Path, overrides: list[str], steps: int = 4000,
             truth: Path = SAMPLE / "gt_mesh.ply", poses_from: Path | None = None) -> tuple[dict, dict]:
    """`recon run IMAGES --out SCENE --preset fast` (SCENE made anew) for a fixed number of steps, not the time budget
    (the steps must not depend on the machine's load), then `recon eval --gt-mesh` against the true surface (the
    sample's, or `truth` with its transforms.json beside it): (the field's metrics.json, the mesh's accuracy).
    poses_from: an earlier run's scene whose poses (SfM differs from run to run) SCENE starts from: the run starts at
    normalize, so they are used even where the poses stage's version changed since."""
    shutil.rmtree(scene, ignore_errors=True)
    if poses_from is not None:
        scene.mkdir(parents=True)
        shutil.copytree(poses_from / "01_poses", scene / "01_poses")
        shutil.copy2(poses_from / "manifest.json", scene / "manifest.json")
    sets = [a for o in ["train.budget=", f"train.steps={steps}", *overrides] for a in ("--set", o)]
    start = ["--from", "normalize"] if poses_from is not None else []
    recon("run", str(images), "--out", str(scene), "--preset", "fast", "-q", *start, *sets)
    recon("eval", str(scene), "--gt-mesh", str(truth))
    return (json.loads((scene / "03_field" / "metrics.json").read_text()),
            json.loads((scene / "eval" / "mesh_accuracy.json").read_text()))


def scene_of(work: Path, label: str) -> Path:
    """The scene folder of the run labelled `label` in `work` (`run_fast`'s SCENE)."""
    return work / f"scene-{label.replace(' ', '_').replace(',', '').replace('=', '_')}"


def sample_run_parser(doc: str, required: bool = True) -> argparse.ArgumentParser:
    """The arguments of a benchmark that runs a variant of the sample (`run_fast`) and appends a row to a record
    (--name and --label not `required` where the script can also do something else)."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--name", required=required)
    parser.add_argument("--label", required=required)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    return parser


def main() -> None:
    parser = sample_run_parser(__doc__)
    parser.add_argument("--shake", type=float, default=SHAKE, help="the shake's length over the width (0: none)")
    args = parser.parse_args()
    from mixed_orientation import append_row
    from recon.app.bench import provenance

    where, load = provenance(), [round(x, 2) for x in os.getloadavg()]
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    make_capture(args.work / "images", args.shake)
    scene = args.work / f"scene-{args.label.replace(' ', '_').replace(',', '')}"
    metrics, accuracy = run_fast(args.work / "images", scene, args.overrides)
    notes = json.loads((scene / "02_scene" / "scene.json").read_text())["notes"]
    row = {"label": args.label, "overrides": args.overrides, "shaken": sorted(SHAKEN), "shake": args.shake,
           "blurred": notes.get("blurred"), "steps": metrics.get("steps"), "rays_per_s": metrics.get("rays_per_s"),
           "psnr": metrics["test"]["psnr"], "ssim": metrics["test"]["ssim"], "fscore_1pct": accuracy.get("fscore@0.01"),
           "fscore_05pct": accuracy.get("fscore@0.005"), "chamfer_rel": accuracy.get("chamfer_l1_rel"),
           **where, "date": date, "load_average_start": load,
           "load_average_end": [round(x, 2) for x in os.getloadavg()]}
    append_row(args.name, row)


if __name__ == "__main__":
    main()
