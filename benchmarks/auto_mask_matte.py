"""How close the automatic masks come to the true matte of the realistic generated tabletop: the graph cut alone (hard,
as segmented) against `recon.capture.auto_masks.matte` at its shipped settings and a few others.

    python benchmarks/auto_mask_matte.py [--work DIR]

Runs poses and normalize on the tabletop's photos (cached in --work), cuts the object out of every photo again
(`segment_object`, the hard masks), then scores each variant against the photo's true matte: its true mask
blurred by the photo's own camera blur (the generator records its sigma). Numbers per variant, averaged over the 14
photos: SAD (sum of absolute differences, thousands of pixels; the matting benchmarks' error), MAE and MSE within
10 px of the true outline, and the IoU of the mask at 0.5. Writes benchmarks/results/auto_mask_matte.json. It
measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one

RESULT = REPO / "benchmarks" / "results" / "auto_mask_matte.json"
BAND_PX = 10
"""The outline band: pixels within this many pixels of the true mask's outline."""
VARIANTS: list[tuple[str, dict[str, float] | None]] = [
    ("cut (hard)", None),
    ("matte (shipped)", {}),
    ("matte, half the radius", {"radius": 0.00375}),
    ("matte, twice the radius", {"radius": 0.015}),
    ("matte, no steepening", {"contrast": 1.0}),
    ("matte, eps 1e-3", {"eps": 1e-3}),
]


def score(found: np.ndarray, truth: np.ndarray, band: np.ndarray) -> dict[str, float]:
    diff = found - truth
    return {"sad_k": float(np.abs(diff).sum() / 1000.0), "band_mae": float(np.abs(diff[band]).mean()),
            "band_mse": float((diff[band] ** 2).mean()),
            "iou": float(((found >= 0.5) & (truth >= 0.5)).sum() / max(((found >= 0.5) | (truth >= 0.5)).sum(), 1))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "recon" / "bench" / "auto_mask_matte")
    args = parser.parse_args()

    import cv2

    from recon.app.bench import prepare_scene, provenance, resolve_dataset
    from recon.app.progress import Reporter
    from recon.atomic import write_json_atomic
    from recon.capture.auto_masks import matte, segment_object
    from recon.capture.images import read_image
    from recon.capture.normalization import normalize
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import load_config

    where = provenance()  # before anything runs: the record below is a tracked file
    load = [round(x, 2) for x in os.getloadavg()]
    started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    _, gt_mesh = resolve_dataset("tabletop_realistic")
    capture = gt_mesh.parent
    blur = [p["blur_sigma_px"] for p in json.loads((capture / "scene_info.json").read_text())["photos"]]
    config = load_config("fast", [])
    base = prepare_scene("tabletop_realistic", args.work, config, Reporter(quiet=True))
    scene = normalize(load_scene(base / "01_poses", recorded_source(base)), config.normalize)  # the masks' scene
    found = segment_object(scene)
    sums: dict[str, list[dict[str, float]]] = {name: [] for name, _ in VARIANTS}
    for frame in scene.frames:
        i = int(frame.stem.rsplit("_", 1)[1])
        true = cv2.imread(str(capture / "masks" / f"{frame.stem}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
        truth = cv2.GaussianBlur(true, (0, 0), blur[i]) if blur[i] > 0.05 else true
        outline = (true >= 0.5).astype(np.uint8) ^ cv2.erode((true >= 0.5).astype(np.uint8), np.ones((3, 3), np.uint8))
        band = cv2.dilate(outline, np.ones((2 * BAND_PX + 1,) * 2, np.uint8)).astype(bool)
        photo = read_image(scene.image_path(frame))
        cut = found.masks[frame.name]
        for name, settings in VARIANTS:
            mask = cut.astype(np.float32) if settings is None else matte(cut, photo, **settings)
            sums[name].append(score(mask, truth, band))
    rows: list[dict[str, Any]] = []
    for name, settings in VARIANTS:
        per = sums[name]
        rows.append({"name": name, "settings": settings, "date": started, **where, "load_average_start": load,
                     "data": "tabletop_realistic", "photos": len(per), "band_px": BAND_PX,
                     **{k: round(float(np.mean([p[k] for p in per])), 5) for k in per[0]}})
        print(f"{name:26s} SAD {rows[-1]['sad_k']:6.2f}k  band MAE {rows[-1]['band_mae']:.4f}  "
              f"band MSE {rows[-1]['band_mse']:.5f}  IoU {rows[-1]['iou']:.4f}")
    write_json_atomic(RESULT, rows)
    print(f"wrote {RESULT}")


if __name__ == "__main__":
    main()
