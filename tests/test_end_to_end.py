"""The real pipeline on the shipped sample: SfM poses vs the true ones, caching, re-runs on change, status."""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from recon.app.cli import app
from recon.capture.scene import load_scene
from recon.geometry.compare import fit_sim3
from tests import faults

SAMPLE = Path(__file__).resolve().parents[1] / "fixtures" / "sample"
runner = CliRunner()


def recon(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def posed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, float]:
    """The sample photos (a copy we may edit) run through poses + normalize once for the module."""
    root = tmp_path_factory.mktemp("e2e")
    photos = root / "photos"
    shutil.copytree(SAMPLE / "images", photos)
    scene = root / "scene"
    t0 = time.perf_counter()
    recon("run", str(photos), "--out", str(scene), "--until", "normalize", "-q")
    return photos, scene, time.perf_counter() - t0


def test_sfm_poses_match_the_true_poses(posed: tuple[Path, Path, float]) -> None:
    _, scene_dir, _ = posed
    summary = json.loads((scene_dir / "manifest.json").read_text())["stages"]["poses"]["summary"]
    assert summary["registered"] == summary["total"] == 40
    ours = load_scene(scene_dir / "01_poses")
    truth = json.loads((SAMPLE / "transforms.json").read_text())
    true_c2w = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"]) for f in truth["frames"]}
    names = [f.name for f in ours.frames]
    src = np.stack([f.c2w[:3, 3] for f in ours.frames])
    dst = np.stack([true_c2w[n][:3, 3] for n in names])
    s, R, t = fit_sim3(src, dst)
    pos_err = np.linalg.norm((s * src @ R.T + t) - dst, axis=1)
    spread = np.linalg.norm(dst - dst.mean(0), axis=1).mean()
    assert np.median(pos_err) / spread < 0.01
    rot_err = []
    for f, n in zip(ours.frames, names, strict=True):
        delta = (R @ f.c2w[:3, :3]).T @ true_c2w[n][:3, :3]
        rot_err.append(np.degrees(np.arccos(np.clip((np.trace(delta) - 1) / 2, -1, 1))))
    assert np.median(rot_err) < 1.0


def test_normalized_sample_is_an_upright_object(posed: tuple[Path, Path, float]) -> None:
    scene = load_scene(posed[1] / "02_scene")
    assert scene.capture == "object"
    assert {s: len(scene.split(s)) for s in ("train", "val", "test")} == {"train": 35, "val": 0, "test": 5}
    ups = np.stack([f.c2w[:3, 1] for f in scene.frames])
    assert ups[:, 2].mean() > 0.8
    assert all(0 < f.near < f.far for f in scene.frames)


def test_rerun_is_cached_and_fast(posed: tuple[Path, Path, float]) -> None:
    photos, scene, first = posed
    t0 = time.perf_counter()
    out = recon("run", str(photos), "--out", str(scene), "--until", "normalize")
    assert time.perf_counter() - t0 < 0.05 * first + 0.5
    assert out.count("cached") >= 2
    status = recon("status", str(scene))
    assert status.count("done") >= 2


def test_status_reads_a_scene_without_loading_torch(posed: tuple[Path, Path, float]) -> None:
    """`recon status` imported every stage (torch, trimesh: 4 s) to read the manifest; the stages load when they run."""
    _, scene, _ = posed
    proc = faults.recon_noting_torch("status", str(scene))
    assert proc.stdout.split()[-5:] == ["exit", "0", "torch", "loaded", "False"], proc.stdout + proc.stderr
    rows = {line.split()[1]: line.split()[3] for line in proc.stdout.splitlines() if line.startswith("│ ")}
    assert {k: rows.get(k) for k in ("poses", "normalize", "train", "mesh")} == {
        "poses": "done", "normalize": "done", "train": "missing", "mesh": "missing"}, proc.stdout

def test_normalize_option_change_reruns_normalize_not_poses(posed: tuple[Path, Path, float]) -> None:
    photos, scene, _ = posed
    before = json.loads((scene / "manifest.json").read_text())["stages"]["poses"]["finished"]
    out = recon("run", str(photos), "--out", str(scene), "--until", "normalize", "--set", "normalize.box_margin=0.2")
    after = json.loads((scene / "manifest.json").read_text())["stages"]
    assert after["poses"]["finished"] == before
    assert after["normalize"]["config"]["box_margin"] == 0.2
    assert "poses: up to date" in out


def test_moved_photos_keep_their_poses(posed: tuple[Path, Path, float]) -> None:
    """The scene names the photos by their place in the photos folder: the same photos moved elsewhere keep every
    stage (they re-ran SfM), and the scene then reads them from the new folder."""
    photos, scene, _ = posed
    recon("run", str(photos), "--out", str(scene), "--until", "normalize", "-q")  # as the default options make it
    moved = photos.parent / "moved" / "photos taken"
    moved.parent.mkdir()
    photos.rename(moved)
    try:
        out = recon("run", str(moved), "--out", str(scene), "--until", "normalize")
        assert "poses: up to date" in out and "normalize: up to date" in out, out
        assert f"read from {moved} now" in " ".join(out.split()), out
        assert json.loads((scene / "manifest.json").read_text())["source"] == str(moved)  # where later commands look
        for folder in ("01_poses", "02_scene"):
            assert str(photos) not in (scene / folder / "scene.json").read_text()
            found = load_scene(scene / folder, moved)
            assert len(found.frames) == 40 and all(found.image_path(f).parent == moved for f in found.frames)
            assert all(found.image_path(f).is_file() for f in found.frames)
        assert "not there" not in recon("status", str(scene))
    finally:
        moved.rename(photos)


def test_removing_a_photo_reruns_poses(posed: tuple[Path, Path, float]) -> None:
    photos, scene, _ = posed
    (photos / "view_039.jpg").unlink()
    recon("run", str(photos), "--out", str(scene), "--until", "normalize", "-q")
    summary = json.loads((scene / "manifest.json").read_text())["stages"]["poses"]["summary"]
    assert summary["total"] == 39


def test_photos_taken_sideways_share_the_camera_and_keep_their_poses(tmp_path: Path) -> None:
    """The sample cut to 400x300, every third photo then turned a quarter as if the phone were held sideways: SfM
    sees those turned back, so all share one camera (it was one a photo, without EXIF), and their poses come out
    rolled a quarter about the axis, their intrinsics those of the photo as it is."""
    from recon.capture.scene import QUARTER_TURN

    photos = tmp_path / "photos"
    photos.mkdir()
    turned = set()
    for i, path in enumerate(sorted((SAMPLE / "images").iterdir())):
        with Image.open(path) as img:
            cut = img.crop((0, 50, 400, 350))
            if i % 3 == 0:
                cut, _ = cut.transpose(Image.Transpose.ROTATE_90), turned.add(path.name)
            cut.save(photos / path.name, quality=95)
    out = recon("run", str(photos), "--out", str(tmp_path / "scene"), "--until", "poses")
    assert "14 of 40 photos are 300x400 where most are 400x300" in " ".join(out.split()), out
    summary = json.loads((tmp_path / "scene" / "manifest.json").read_text())["stages"]["poses"]["summary"]
    assert summary["registered"] == 40 and summary["cameras"] == 1
    ours = load_scene(tmp_path / "scene" / "01_poses", photos)
    truth = json.loads((SAMPLE / "transforms.json").read_text())
    true_c2w = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"]) for f in truth["frames"]}
    for name in turned:
        true_c2w[name][:3, :3] = true_c2w[name][:3, :3] @ QUARTER_TURN.T
    src = np.stack([f.c2w[:3, 3] for f in ours.frames])
    s, R, t = fit_sim3(src, np.stack([true_c2w[f.name][:3, 3] for f in ours.frames]))
    rot_err = {f.name: np.degrees(np.arccos(np.clip((np.trace((R @ f.c2w[:3, :3]).T @ true_c2w[f.name][:3, :3]) - 1)
                                                    / 2, -1, 1))) for f in ours.frames}
    assert max(rot_err[n] for n in turned) < 1.5 and np.median(list(rot_err.values())) < 1.0, rot_err
    for frame in ours.frames:
        assert (frame.w, frame.h) == ((300, 400) if frame.name in turned else (400, 300))
        cx, cy = (150, 200) if frame.name in turned else (200, 150)  # the true centre of the cut, turned with it
        assert abs(frame.cx - cx) < 8 and abs(frame.cy - cy) < 8 and abs(frame.fl_x / 482.84 - 1) < 0.03
