"""What `train.appearance=auto` measures on each capture: the photos' exposure spread (recon.nerf.appearance) with the
photos matched to their nearest cameras only, and to those plus far partners facing the same way, one after the other.

    python benchmarks/exposure_pairs.py --capture fox --capture lego-half --capture sample \
        --capture tabletop_realistic --capture tabletop_painted --capture tabletop_video --name exposure_pairs

Each capture's photos are read at the fast preset's 400-px long side (recon.capture.images.read_image) with their
reference or true poses (no SfM), as the train stage reads its training photos: the fox's 67, the Lego's 100 training
views, the sample's 40, a generated capture's photos (``recon bench`` renders and caches them) and every fourth frame
of the generated clip (its exposure follows the light slowly). A row holds the pairs matched, the pairs that differ by
more than the threshold themselves, the photos whose fitted gain does, the largest fitted gain, what `auto` decides,
the seconds, and for a generated capture the fitted log gains against the true ones (median and largest error, the
photos the truth calls changed). Writes benchmarks/results/<name>.json after each row.
It measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data"
MAX_SIDE = 400
VIDEO_STRIDE = 4


def _read(path: Path) -> np.ndarray:
    """The photo as the train stage reads it: float RGB(A) in [0, 1], EXIF-oriented, its long side at most MAX_SIDE."""
    from recon.capture.images import read_image

    return read_image(path, MAX_SIDE)


def _transforms(folder: Path, name: str = "transforms.json") -> tuple[list[Path], np.ndarray]:
    doc = json.loads((folder / name).read_text())
    paths = []
    for frame in doc["frames"]:
        path = folder / frame["file_path"]
        paths.append(path if path.suffix else path.with_suffix(".png"))
    return paths, np.array([f["transform_matrix"] for f in doc["frames"]], dtype=np.float64)


def _true_log_gains(info: Path, count: int) -> np.ndarray | None:
    if not info.is_file():
        return None
    gains = json.loads(info.read_text()).get("gains")
    return np.log(np.asarray(gains, dtype=np.float64))[:count] if gains else None


def load_capture(name: str) -> tuple[list[np.ndarray], np.ndarray, np.ndarray | None]:
    """(photos, camera-to-world (n, 4, 4), true per-photo log gains (n, 3) or None)."""
    if name == "fox":
        paths, c2w = _transforms(SHARED / "fox")
        return [_read(p) for p in paths], c2w, None
    if name == "lego-half":
        paths, c2w = _transforms(SHARED / "nerf_synthetic_lego_half", "transforms_train.json")
        return [_read(p) for p in paths], c2w, None
    if name == "sample":
        paths, c2w = _transforms(REPO / "fixtures" / "sample")
        return [_read(p) for p in paths], c2w, None
    from recon.app.bench import resolve_dataset

    source, gt_mesh = resolve_dataset(name)
    capture = gt_mesh.parent
    if name.startswith("tabletop_video"):
        return _video_frames(source, capture)
    paths, c2w = _transforms(capture)
    return [_read(p) for p in paths], c2w, _true_log_gains(capture / "scene_info.json", len(paths))


def _video_frames(clip: Path, capture: Path) -> tuple[list[np.ndarray], np.ndarray, np.ndarray | None]:
    """Every VIDEO_STRIDE-th frame of the clip with its true pose and exposure (transforms.json and video_info.json
    list every frame in order; the clip keeps one white balance)."""
    import cv2

    from recon.capture.images import resize

    doc = json.loads((capture / "transforms.json").read_text())
    poses = np.array([f["transform_matrix"] for f in doc["frames"]], dtype=np.float64)
    reader = cv2.VideoCapture(str(clip))
    images, keep = [], []
    index = 0
    while True:
        ok, frame = reader.read()
        if not ok:
            break
        if index % VIDEO_STRIDE == 0 and index < len(poses):
            h, w = frame.shape[:2]
            scale = min(1.0, MAX_SIDE / max(h, w))
            rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
            images.append(resize(rgb, (round(w * scale), round(h * scale))))
            keep.append(index)
        index += 1
    reader.release()
    info = json.loads((clip.parent.parent / "video_info.json").read_text())
    truth = np.log(np.asarray(info["exposures"], dtype=np.float64)[keep])[:, None].repeat(3, axis=1)
    return images, poses[keep], truth


def measure(images: list[np.ndarray], c2w: np.ndarray, far: int, truth: np.ndarray | None) -> dict[str, Any]:
    from recon.nerf.appearance import decide, exposure_spread

    start = time.perf_counter()
    spread = exposure_spread(images, c2w, far=far)
    seconds = time.perf_counter() - start
    on, why = decide("auto", spread)
    row: dict[str, Any] = {
        "photos": spread.n, "far_partners": far, "pairs": spread.pairs, "pairs_changed": spread.pairs_changed,
        "pairs_changed_fraction": round(spread.pairs_changed / max(spread.pairs, 1), 4),
        "photos_changed": spread.changed, "largest_log_gain": round(spread.largest, 4), "auto": "on" if on else "off",
        "seconds": round(seconds, 2), "reason": why,
    }
    if truth is not None:
        true = truth - np.median(truth, axis=0)
        error = np.abs(spread.log_gain - true).max(axis=1)
        row.update({"log_gain_error_median": round(float(np.median(error)), 4),
                    "log_gain_error_largest": round(float(error.max()), 4),
                    "photos_changed_truly": int((np.abs(true).max(axis=1) > spread.threshold).sum())})
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", action="append", required=True,
                        help="fox, lego-half, sample or a generated data set of recon bench (e.g. tabletop_painted)")
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    from recon.app.bench import provenance
    from recon.nerf.appearance import FAR_PARTNERS

    out = REPO / "benchmarks" / "results" / f"{args.name}.json"
    where, rows = provenance(), []
    for name in args.capture:
        images, c2w, truth = load_capture(name)
        for far in (0, FAR_PARTNERS):
            load = [round(x, 2) for x in os.getloadavg()]
            date = datetime.now(timezone.utc).isoformat(timespec="seconds")
            row = {"capture": name, **measure(images, c2w, far, truth), **where, "date": date,
                   "load_average_start": load}
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k not in ("reason", "machine")}), flush=True)
            out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
