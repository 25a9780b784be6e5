"""Imports into the scene contract, and normalization's invariances."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon.camera import look_at
from recon.capture.normalization import normalize, rotation_between, similarity, transform_c2w
from recon.capture.scene import (
    Frame,
    Scene,
    detect_source,
    import_nerf_synthetic,
    import_npz,
    import_transforms,
    load_scene,
)
from recon.config import NormalizeConfig
from recon.errors import InputError


def ring_scene(n: int = 24, radius: float = 4.0, seed: int = 0, with_points: bool = True) -> Scene:
    """Cameras on a ring around an object at the origin (the object: points in a unit ball)."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = np.radians(20 + 15 * np.sin(3 * az))
        eye = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        frames.append(Frame(f"/p/{i:03d}.jpg", look_at(eye, np.zeros(3)), 400.0, 400.0, 200.0, 150.0, 400, 300))
    points = rng.normal(size=(2000, 3)) * 0.3 if with_points else np.zeros((0, 3))
    return Scene(frames=frames, points=points, point_colors=np.zeros((len(points), 3), np.uint8))


def transformed(scene: Scene, T: np.ndarray) -> Scene:
    frames = [Frame(**{**f.__dict__, "c2w": transform_c2w(T, f.c2w)}) for f in scene.frames]
    pts = scene.points @ T[:3, :3].T + T[:3, 3]
    return Scene(frames=frames, points=pts, point_colors=scene.point_colors)


def random_rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e4])
@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_normalize_is_invariant_to_scale_translation_rotation(scale: float, offset: float) -> None:
    base = ring_scene()
    ref = normalize(base, NormalizeConfig())
    T = similarity(scale, random_rotation(3), np.zeros(3))
    T[:3, 3] += offset
    moved = normalize(transformed(base, T), NormalizeConfig())
    assert moved.capture == ref.capture == "object"
    for a, b in zip(ref.frames, moved.frames, strict=True):
        assert np.allclose(a.c2w, b.c2w, atol=1e-5)
        assert a.near == pytest.approx(b.near, rel=1e-4) and a.far == pytest.approx(b.far, rel=1e-4)
        assert a.split == b.split
    assert np.allclose(ref.aabb, moved.aabb, atol=1e-5)
    # the stored similarity maps back to the source frame exactly
    src = transformed(base, T)
    back = transform_c2w(moved.source_from_world, moved.frames[5].c2w)
    assert np.allclose(back[:3, 3], src.frames[5].c2w[:3, 3], rtol=1e-9, atol=1e-9 * max(scale, offset, 1))


def test_normalized_scene_is_upright_centred_and_in_the_box() -> None:
    scene = normalize(transformed(ring_scene(), similarity(2.0, random_rotation(7), np.array([5.0, -3, 1]))), NormalizeConfig())
    ups = np.stack([f.c2w[:3, 1] for f in scene.frames])
    assert ups.mean(0)[2] > 0.9  # cameras' up points +Z
    assert np.abs(scene.aabb).max() == pytest.approx(1.0)
    centre_pts = np.median(scene.points, axis=0)
    assert np.linalg.norm(centre_pts) < 0.1
    for f in scene.frames:
        assert 0 < f.near < f.far


def test_split_is_deterministic_and_holds_out() -> None:
    a = normalize(ring_scene(), NormalizeConfig())
    b = normalize(ring_scene(), NormalizeConfig())
    assert [f.split for f in a.frames] == [f.split for f in b.frames]
    counts = {s: len(a.split(s)) for s in ("train", "val", "test")}
    assert counts == {"train": 21, "val": 0, "test": 3}  # no validation photos by default: they train


def test_forward_facing_capture_is_unbounded() -> None:
    frames = [Frame(f"/p/{i}.jpg", look_at(np.array([i * 0.1, 0, 0]), np.array([i * 0.1, 10.0, 0])), 300, 300, 150, 100, 300, 200) for i in range(12)]
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-3, 3, 500), rng.uniform(5, 30, 500), rng.uniform(-2, 2, 500)]
    scene = normalize(Scene(frames=frames, points=pts), NormalizeConfig())
    assert scene.capture == "unbounded"
    assert all(0 < f.near < f.far for f in scene.frames)


def test_without_points_box_comes_from_cameras() -> None:
    scene = normalize(ring_scene(with_points=False), NormalizeConfig())
    assert scene.capture == "object"
    assert np.abs(scene.aabb).max() == pytest.approx(1.0)
    assert "cameras" in scene.notes["box"]


def test_rotation_between_handles_opposite_vectors() -> None:
    for a, b in [([0, 0, 1], [0, 0, -1]), ([1, 0, 0], [0, 1, 0]), ([0, 0, 1], [0, 0, 1])]:
        R = rotation_between(np.array(a, float), np.array(b, float))
        assert np.allclose(R @ np.array(a, float), b, atol=1e-9)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)


def test_scene_roundtrip(tmp_path: Path) -> None:
    scene = normalize(ring_scene(), NormalizeConfig())
    scene.save(tmp_path)
    loaded = load_scene(tmp_path)
    assert len(loaded.frames) == len(scene.frames)
    assert np.allclose(loaded.frames[3].c2w, scene.frames[3].c2w)
    assert np.allclose(loaded.world_from_source, scene.world_from_source)
    assert np.allclose(loaded.points, scene.points)
    assert scene.region_points is not None and scene.region_points.any()  # the object's points, kept for its masks
    assert np.array_equal(loaded.region_points, scene.region_points)
    assert np.array_equal(loaded.aside_points, scene.aside_points)
    doc = json.loads((tmp_path / "scene.json").read_text())
    assert doc["fl_x"] == 400.0 and "transform_matrix" in doc["frames"][0]  # transforms.json-compatible


def test_nerf_synthetic_import_reproduces_poses_exactly(shared_data: Path) -> None:
    folder = shared_data / "nerf_synthetic_lego_half"
    scene = import_nerf_synthetic(folder)
    for split, n in (("train", 100), ("val", 100), ("test", 200)):
        doc = json.loads((folder / f"transforms_{split}.json").read_text())
        frames = scene.split(split)
        assert len(frames) == n
        for f, fd in zip(frames, doc["frames"], strict=True):
            assert np.allclose(f.c2w, np.asarray(fd["transform_matrix"]), atol=1e-6)
            assert Path(f.file_path).stem == Path(fd["file_path"]).name
    assert scene.frames[0].fl_x == pytest.approx(555.5555, rel=1e-5)
    assert scene.has_alpha


def _write_capture(tmp_path: Path, n: int = 3) -> Path:
    from PIL import Image

    folder = tmp_path / "cap"
    (folder / "images").mkdir(parents=True)
    for i in range(n):
        Image.new("RGB", (64, 48), (i * 40, 100, 50)).save(folder / "images" / f"{i}.png")
    return folder


def test_transforms_import_and_bad_documents(tmp_path: Path) -> None:
    folder = _write_capture(tmp_path)
    good = {
        "camera_angle_x": 0.8,
        "frames": [{"file_path": f"images/{i}.png", "transform_matrix": look_at(np.array([3.0, i, 1]), np.zeros(3)).tolist()} for i in range(3)],
    }
    (folder / "transforms.json").write_text(json.dumps(good))
    assert detect_source(folder) == "transforms"
    scene = import_transforms(folder)
    assert (scene.frames[0].w, scene.frames[0].h) == (64, 48)

    def bad(doc: dict, match: str) -> None:
        (folder / "transforms.json").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=match):
            import_transforms(folder)

    frame0 = good["frames"][0]
    bad({"frames": []}, "no 'frames'")
    bad({**good, "frames": [{**frame0, "transform_matrix": [[1, 0], [0, 1]]}]}, "shape")
    nan = np.eye(4)
    nan[0, 3] = np.nan
    bad({**good, "frames": [{**frame0, "transform_matrix": nan.tolist()}]}, "NaN")
    bad({**good, "frames": [{**frame0, "transform_matrix": (np.eye(4) * 2).tolist()}]}, "not orthonormal|row")
    bad({**good, "frames": [{**frame0, "file_path": "../../etc/passwd"}]}, "outside the capture folder")
    bad({**good, "frames": [{**frame0, "file_path": "images/missing.png"}]}, "does not exist")
    bad({"frames": [frame0]}, "no focal length")
    (folder / "transforms.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        import_transforms(folder)


def test_npz_import(tmp_path: Path) -> None:
    n, h, w = 4, 40, 50
    poses = np.stack([look_at(np.array([4.0, i, 1]), np.zeros(3)) for i in range(n)])
    path = tmp_path / "tiny.npz"
    np.savez(path, images=np.random.default_rng(0).random((n, h, w, 3)).astype(np.float32), poses=poses, focal=np.array(60.0))
    scene = import_npz(path, tmp_path / "imgs")
    assert len(scene.frames) == n and scene.frames[0].fl_x == 60.0 and scene.frames[0].w == w
    assert np.allclose(scene.frames[2].c2w, poses[2])
    np.savez(path, images=np.zeros((n, h, w, 3)), poses=poses[:2], focal=60.0)
    with pytest.raises(InputError, match="poses"):
        import_npz(path, tmp_path / "imgs2")
    np.savez(path, poses=poses, focal=60.0)
    with pytest.raises(InputError, match="missing array"):
        import_npz(path, tmp_path / "imgs3")


def test_stored_paths_name_the_photos_by_their_place_in_the_input_folder(tmp_path: Path) -> None:
    """A photo in the input's folder, or a mask beside it, is stored as `{source}/…` and found in the folder the input
    is read from now; a file elsewhere stays absolute, and a marked path with no folder said is a clear error."""
    from recon.capture.scene import SOURCE_MARK, stored_path

    capture = tmp_path / "capture"
    (capture / "photos").mkdir(parents=True)
    (capture / "masks").mkdir()
    photo, mask = capture / "photos" / "p 1.jpg", capture / "masks" / "p 1.png"
    far = tmp_path / "elsewhere" / "x.jpg"
    assert stored_path(photo, capture / "photos") == f"{SOURCE_MARK}/p 1.jpg"
    assert stored_path(mask, capture / "photos") == f"{SOURCE_MARK}/../masks/p 1.png"
    assert stored_path(far, capture / "photos") == str(far)  # two folders up: not the capture's
    assert stored_path(capture / "clip.mp4", capture / "clip.mp4") == f"{SOURCE_MARK}/clip.mp4"  # a file input
    frame = Frame(stored_path(photo, capture / "photos"), np.eye(4), 50.0, 50.0, 20.0, 15.0, 40, 30,
                  mask_path=stored_path(mask, capture / "photos"))
    Scene(frames=[frame]).save(tmp_path)
    moved = tmp_path / "moved" / "photos"
    scene = load_scene(tmp_path, moved)
    assert scene.frames[0].name == "p 1.jpg"
    assert scene.image_path(scene.frames[0]) == moved / "p 1.jpg"
    assert scene.mask_file(scene.frames[0]) == moved.parent / "masks" / "p 1.png"
    with pytest.raises(InputError, match="input folder"):
        load_scene(tmp_path).image_path(scene.frames[0])


def test_a_pose_found_on_a_turned_copy_is_turned_back_to_the_photo() -> None:
    """SfM sees a sideways photo turned a quarter (`np.rot90`) to share the others' camera: the frame made from it
    projects every point where the turned copy put it, moved back (pixel (x, y) of the copy is (h - y, x) of the
    photo), the lens's radial and tangential distortion included."""
    import cv2
    from scipy.spatial.transform import Rotation

    from recon.capture.scene import frame_from_sfm

    def project(frame: Frame, points: np.ndarray) -> np.ndarray:
        c2w_cv = frame.c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
        w2c = np.linalg.inv(c2w_cv)
        K = np.array([[frame.fl_x, 0, frame.cx], [0, frame.fl_y, frame.cy], [0, 0, 1]])
        return cv2.projectPoints(points.reshape(-1, 1, 3), cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], K,
                                 np.array(frame.distortion))[0].reshape(-1, 2)

    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = Rotation.random(random_state=1).as_matrix(), [1.0, 2.0, 3.0]
    copy = {"c2w": c2w, "w": 640, "h": 480, "fl_x": 500.0, "fl_y": 520.0, "cx": 330.0, "cy": 230.0, "k1": 0.05,
            "k2": -0.02, "p1": 0.003, "p2": -0.002}
    rng = np.random.default_rng(0)
    in_view = np.c_[rng.uniform(-1, 1, (50, 2)), -rng.uniform(2, 4, 50)]  # OpenGL: the camera looks down -Z
    points = in_view @ c2w[:3, :3].T + c2w[:3, 3]
    seen = project(frame_from_sfm("a.jpg", copy), points)
    photo = frame_from_sfm("a.jpg", copy, 2.0, 2.0, turned=True)  # the photo twice the copy's size
    assert (photo.w, photo.h) == (960, 1280)
    np.testing.assert_allclose(project(photo, points), 2.0 * np.c_[480 - seen[:, 1], seen[:, 0]], atol=1e-6)
    np.testing.assert_allclose(photo.center, c2w[:3, 3])
    image = np.zeros((3, 5))  # the pixel mapping is np.rot90's, which turns the copies
    image[1, 3] = 1.0
    y, x = np.argwhere(np.rot90(image))[0]
    assert (5 - 1 - y, x) == (3, 1)
