"""How sharp each photo of a real capture measures against the photos that share its view, and how far a shake
brings it down: the calibration of `recon.capture.blur.BLURRED_SHARE`.

    python benchmarks/blur_shares.py SCENE PHOTOS --name blur_shares_fox

SCENE: a scene whose poses stage ran on the photos folder PHOTOS (e.g. `recon run ../shared/data/fox/images --out
SCENE --until poses`). Writes each photo's sharpness share as it is (`sharpness_shares`), then, for every 7th photo,
its share with the photo shaken along a line of 3, 5 and 9 px at the analysis side (0.5-1.4% of its width) in its
own direction, the others as they are, to benchmarks/results/NAME.json with the commit and machine. It measures; it
asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one
sys.path.insert(0, str(REPO / "benchmarks"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("photos", type=Path)
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    import recon.capture.blur as blur
    from blurred_photos import shaken
    from recon.app.bench import provenance
    from recon.capture.images import read_image
    from recon.capture.scene import load_scene
    from recon.capture.video import ANALYSIS_SIDE

    where, load = provenance(), [round(x, 2) for x in os.getloadavg()]
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    scene = load_scene(args.scene / "01_poses", args.photos)
    shares = blur.sharpness_shares(scene, ANALYSIS_SIDE)
    shaken_rows = []
    real_read = blur.read_image
    for i, frame in enumerate(f for f in scene.frames if f.name in shares):
        if i % 7:
            continue
        row = {"photo": frame.name, "as_taken": round(shares[frame.name], 4)}
        for length in (3, 5, 9):
            def read(path: Path, max_side: int | None = None, _name: str = frame.name, _length: int = length):
                image = real_read(path, max_side=max_side)
                if path.name != _name:
                    return image
                return shaken(np.ascontiguousarray(image[..., :3]), 37.0 * i, float(_length))
            blur.read_image = read
            try:
                row[f"shaken_{length}px"] = round(blur.sharpness_shares(scene, ANALYSIS_SIDE)[frame.name], 4)
            finally:
                blur.read_image = real_read
        shaken_rows.append(row)
        print(json.dumps(row), flush=True)
    values = np.array(list(shares.values()))
    record = [{"scene": str(args.scene), "photos": len(shares), "analysis_side": ANALYSIS_SIDE,
               "as_taken": {"min": round(float(values.min()), 4), "p5": round(float(np.percentile(values, 5)), 4),
                            "median": round(float(np.median(values)), 4),
                            "lowest": sorted((round(v, 4), n) for n, v in shares.items())[:5]},
               "shaken": shaken_rows, **where, "date": date, "load_average_start": load}]
    (REPO / "benchmarks" / "results" / f"{args.name}.json").write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record[0]["as_taken"]))


if __name__ == "__main__":
    main()
