"""benchmarks/lego_full_res.py: one NeRF-synthetic folder with full-resolution training photos and half-resolution
test photos, whose cameras recon reads at each photo's own size."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from recon.capture.scene import parse_frames
from tests.scripts import load_script


def _tool():
    return load_script("benchmarks/lego_full_res.py", "lego_full_res")


def _nerf_folder(root: Path, split: str, n: int, side: int) -> None:
    (root / split).mkdir(parents=True)
    frames = []
    for i in range(n):
        Image.fromarray(np.full((side, side, 4), i, np.uint8)).save(root / split / f"r_{i}.png")
        pose = np.eye(4)
        pose[2, 3] = 4.0 + i
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": pose.tolist()})
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))


def test_full_res_training_and_spread_half_res_test_views(tmp_path: Path) -> None:
    full, half, out = tmp_path / "full", tmp_path / "half", tmp_path / "out"
    _nerf_folder(full, "train", 3, 64)
    _nerf_folder(half, "test", 5, 32)
    _nerf_folder(half, "train", 2, 32)  # the half-res training photos are not taken
    assert _tool().build(out, full, half, 3) == {"train": 3, "test": 3}
    test = json.loads((out / "transforms_test.json").read_text())["frames"]
    assert [f["file_path"] for f in test] == ["./test/r_0", "./test/r_2", "./test/r_4"]  # first, middle, last
    assert sorted(p.name for p in (out / "test").iterdir()) == ["r_0.png", "r_2.png", "r_4.png"]
    trains = parse_frames(json.loads((out / "transforms_train.json").read_text()), out, "train", split="train")
    tests = parse_frames(json.loads((out / "transforms_test.json").read_text()), out, "test", split="test")
    assert {(f.w, f.h) for f in trains} == {(64, 64)} and {(f.w, f.h) for f in tests} == {(32, 32)}
    assert trains[0].fl_x == 2 * tests[0].fl_x  # the same camera angle at each photo's own size
