"""`recon export`: each format re-imports (recon's own importers) to the same cameras, in both frames.

The scene is the sample through real SfM (a SIMPLE_RADIAL camera, so the undistortion path runs).
COLMAP's conventions are also checked by hand against images.txt (quaternion → rotation, centre).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from recon.app.cli import app
from recon.app.exports import scene_in_frame
from recon.capture.images import read_image, read_mask, save_image, undistort
from recon.capture.scene import Frame, detect_source, import_colmap, import_transforms, load_scene
from recon.runner.pipeline import recorded_source
from tests.assets_scene import tiny_scene

runner = CliRunner()


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_scene(tmp_path_factory)[1]


def export(scene: Path, fmt: str, out: Path, frame: str = "normalized") -> str:
    result = runner.invoke(app, ["export", str(scene), "--format", fmt, "--frame", frame, "--out", str(out)])
    assert result.exit_code == 0, result.output
    return result.output


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(b).max(), 1e-12))


def assert_same_cameras(got: list[Frame], want: list[Frame]) -> None:
    assert [Path(f.file_path).name for f in got] == [Path(f.file_path).name for f in want]
    for g, w in zip(got, want, strict=True):
        assert rel([g.fl_x, g.fl_y, g.cx, g.cy, g.w, g.h], [w.fl_x, w.fl_y, w.cx, w.cy, w.w, w.h]) <= 1e-6
        assert rel(g.c2w[:3, :3], w.c2w[:3, :3]) <= 1e-6
        assert rel(g.c2w[:3, 3], w.c2w[:3, 3]) <= 1e-6
        assert not any(g.distortion) and g.camera_model == "OPENCV"  # the exported images are undistorted


@pytest.mark.parametrize("frame", ["normalized", "source"])
def test_nerfstudio_export_reimports_to_the_same_cameras(scene_dir: Path, tmp_path: Path, frame: str) -> None:
    out = tmp_path / "ns"
    export(scene_dir, "nerfstudio", out, frame)
    assert detect_source(out) == "transforms"
    want = scene_in_frame(scene_dir, frame).frames
    got = import_transforms(out).frames
    assert_same_cameras(got, want)
    truth = load_scene(scene_dir / ("02_scene" if frame == "normalized" else "01_poses"))
    assert rel(np.stack([f.c2w for f in want]), np.stack([f.c2w for f in truth.frames])) <= 1e-12
    assert [f.split for f in got] == [f.split for f in load_scene(scene_dir / "02_scene").frames]
    assert (out / "points.ply").is_file()


def test_exported_images_are_the_undistorted_photos(scene_dir: Path, tmp_path: Path) -> None:
    # a known, visible barrel distortion on every camera: SfM's own k1 on these pinhole renders is near 0
    # (since the robust final bundle adjustment), too small to move the picture measurably
    scene_copy = tmp_path / "scene"
    shutil.copytree(scene_dir, scene_copy)
    doc = json.loads((scene_copy / "02_scene" / "scene.json").read_text())
    for f in [doc, *doc["frames"]]:
        if "k1" in f:
            f["k1"] = -0.08
    (scene_copy / "02_scene" / "scene.json").write_text(json.dumps(doc))
    scene_dir = scene_copy
    out = tmp_path / "ns"
    export(scene_dir, "nerfstudio", out)
    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    frame = scene.frames[0]
    assert frame.k1 == -0.08
    original = read_image(scene.image_path(frame))
    expected = undistort(original, frame.fl_x, frame.fl_y, frame.cx, frame.cy, frame.distortion)
    exported = read_image(out / "images" / frame.name)
    assert np.abs(exported - expected).mean() < 1.5 / 255  # only the JPEG re-encoding differs
    moved = np.abs(expected - original).max(axis=-1) > 0.1  # where undistortion visibly moved the picture
    assert moved.sum() > 100
    assert np.abs(exported - original)[moved].mean() > 3 * np.abs(exported - expected)[moved].mean()


def test_exported_masks_are_undistorted_like_the_photos_and_inside_the_export(scene_dir: Path, tmp_path: Path) -> None:
    # masks as recon's automatic ones are: half the photos' size, relative to the scene folder; a visible distortion
    scene_copy = tmp_path / "scene"
    shutil.copytree(scene_dir, scene_copy)
    doc = json.loads((scene_copy / "02_scene" / "scene.json").read_text())
    (scene_copy / "02_scene" / "masks").mkdir()
    for f in [doc, *doc["frames"]]:
        if "k1" in f:
            f["k1"] = -0.08
    for f in doc["frames"]:
        w, h = doc.get("w", f.get("w")), doc.get("h", f.get("h"))
        mask = np.zeros((h // 2, w // 2), np.float32)
        mask[2: h // 2 - 2, 2: w // 5] = 1.0  # a band along the left border, where the lens moves the picture most
        name = Path(f["file_path"]).stem + ".png"
        save_image(scene_copy / "02_scene" / "masks" / name, mask)
        f["mask_path"] = f"02_scene/masks/{name}"
    (scene_copy / "02_scene" / "scene.json").write_text(json.dumps(doc))
    out = tmp_path / "ns"
    export(scene_copy, "nerfstudio", out)
    shutil.rmtree(scene_copy)  # the export stands alone
    written = json.loads((out / "transforms.json").read_text())
    paths = [f["mask_path"] for f in written["frames"]]
    assert all(p.startswith("masks/") and p.endswith(".png") and (out / p).is_file() for p in paths)
    assert len(set(paths)) == len(paths)
    reimported = import_transforms(out)
    frame = reimported.frames[0]
    assert reimported.mask_file(frame) == out / paths[0]
    w, h = frame.w, frame.h
    before = np.zeros((h, w), np.float32)
    before[4: h - 4, 4: 2 * (w // 5)] = 1.0  # the band at the photo's size
    scene = load_scene(scene_dir / "02_scene")
    lens = scene.frames[0]
    expected = undistort(before, lens.fl_x, lens.fl_y, lens.cx, lens.cy, (-0.08, *lens.distortion[1:]))
    got = read_mask(out / paths[0], (w, h))
    assert got.shape == (h, w)
    moved = np.abs(expected - before) > 0.5
    assert moved.sum() > 50  # the lens moved the band's edges
    assert np.abs(got - expected)[moved].mean() < 0.2 < np.abs(got - before)[moved].mean()


@pytest.mark.parametrize("frame", ["normalized", "source"])
def test_colmap_export_reimports_to_the_same_cameras_and_points(scene_dir: Path, tmp_path: Path, frame: str) -> None:
    out = tmp_path / "colmap"
    export(scene_dir, "colmap", out, frame)
    assert detect_source(out) == "colmap"
    want = scene_in_frame(scene_dir, frame)
    got = import_colmap(out)
    assert_same_cameras(got.frames, want.frames)
    assert len(got.points) == len(want.points) > 100
    assert rel(got.points, want.points) <= 1e-6
    assert np.array_equal(got.point_colors, want.point_colors)


def test_colmap_images_txt_follows_colmap_conventions(scene_dir: Path, tmp_path: Path) -> None:
    """World-to-camera qw qx qy qz tx ty tz, OpenCV axes: centre = -Rᵀt, the camera's +Z is the viewing direction."""
    out = tmp_path / "colmap"
    export(scene_dir, "colmap", out)
    lines = [ln for ln in (out / "sparse" / "0" / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    records = {ln.split()[9]: [float(x) for x in ln.split()[1:8]] for ln in lines if len(ln.split()) >= 10}
    scene = load_scene(scene_dir / "02_scene")
    assert len(records) == len(scene.frames)
    for f in scene.frames:
        qw, qx, qy, qz, *t = records[f.name]
        R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        assert np.allclose(-R.T @ np.asarray(t), f.center, atol=1e-9)
        assert np.allclose(R[2], -f.c2w[:3, 2], atol=1e-9)  # OpenCV +Z forward = OpenGL -Z
        assert np.allclose(R[1], -f.c2w[:3, 1], atol=1e-9)  # OpenCV +Y down = OpenGL -Y
    cams = [ln for ln in (out / "sparse" / "0" / "cameras.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    assert cams[0].split()[1] == "PINHOLE"


def test_points_export_is_the_sparse_cloud(scene_dir: Path, tmp_path: Path) -> None:
    import trimesh

    out = tmp_path / "pts"
    export(scene_dir, "points", out)
    cloud = trimesh.load(out / "points.ply")
    scene = load_scene(scene_dir / "02_scene")
    assert rel(cloud.vertices, scene.points) <= 1e-6
    assert np.array_equal(np.asarray(cloud.colors)[:, :3], scene.point_colors)


def test_export_refuses_a_folder_it_did_not_make_and_replaces_its_own(scene_dir: Path, tmp_path: Path) -> None:
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    result = runner.invoke(app, ["export", str(scene_dir), "--format", "points", "--out", str(foreign)])
    assert result.exit_code == 2
    assert "did not export" in result.output and (foreign / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]

    ours = tmp_path / "ours"
    export(scene_dir, "points", ours)
    export(scene_dir, "colmap", ours)  # an earlier recon export is replaced whole
    assert not (ours / "points.ply").exists() and detect_source(ours) == "colmap"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-export")]


def test_export_of_a_folder_that_is_no_scene_is_a_clear_error(tmp_path: Path) -> None:
    result = runner.invoke(app, ["export", str(tmp_path), "--format", "colmap", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "not a recon scene folder" in result.output
    result = runner.invoke(app, ["export", str(tmp_path), "--format", "ply", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "--format must be one of" in result.output
