"""The full-resolution Lego to train on, with half-resolution test views to score on: one NeRF-synthetic folder.

    python benchmarks/lego_full_res.py --out .dev/lego_full                       # 100 train at 800², 50 test at 400²
    python benchmarks/gpu_check.py --data .dev/lego_full --preset quality --budget 5m --columns default --out DIR

Issue 37's second target is `quality` on the 800² Lego. ../shared/data/nerf_synthetic_lego holds only its training
photos (42 MB); its test poses are those of the half-resolution set, whose test photos are 400² renders of the same
cameras. recon reads each photo's size and derives its focal length from it (`camera_angle_x`), so one folder can hold
both: it trains at 800² (quality's max_side) and scores at 400². Copies, not links: a device machine's `carry` takes
files. The test views are spread evenly over the 200: a device call carries the checkout (~13 MB), the wheels and this
folder in 64 MiB, and 100 test views (42 + 13 MB) already passed it.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def build(out: Path, full: Path, half: Path, test_views: int) -> dict[str, int]:
    """Write `out`: full's training split (photos and transforms_train.json) and `test_views` of half's test split
    (spread evenly). Returns how many photos of each split it holds."""
    train_doc = json.loads((full / "transforms_train.json").read_text())
    test_doc = json.loads((half / "transforms_test.json").read_text())
    frames = test_doc["frames"]
    keep = sorted({round(i * (len(frames) - 1) / max(1, test_views - 1)) for i in range(test_views)}) if test_views else []
    test_doc["frames"] = [frames[i] for i in keep]
    (out / "train").mkdir(parents=True, exist_ok=True)
    (out / "test").mkdir(exist_ok=True)
    for doc, source, split in ((train_doc, full, "train"), (test_doc, half, "test")):
        for frame in doc["frames"]:
            name = Path(frame["file_path"]).name + ".png"
            shutil.copyfile(source / split / name, out / split / name)
        (out / f"transforms_{split}.json").write_text(json.dumps(doc, indent=1))
    return {"train": len(train_doc["frames"]), "test": len(test_doc["frames"])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the folder to write (made if missing)")
    parser.add_argument("--full", type=Path, default=SHARED / "nerf_synthetic_lego")
    parser.add_argument("--half", type=Path, default=SHARED / "nerf_synthetic_lego_half")
    parser.add_argument("--test-views", type=int, default=50, help="half-res test views to copy (of 200)")
    args = parser.parse_args(argv)
    for folder, needs in ((args.full, "transforms_train.json"), (args.half, "transforms_test.json")):
        if not (folder / needs).is_file():
            print(f"error: {folder} has no {needs}: pass --full / --half with the NeRF-synthetic Lego folders",
                  file=sys.stderr)
            return 2
    counts = build(args.out, args.full, args.half, args.test_views)
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(f"{args.out}: {counts['train']} training photos at full resolution, {counts['test']} test photos at half, "
          f"{size / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
