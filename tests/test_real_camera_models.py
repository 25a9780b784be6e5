"""Imported camera models: a fisheye transforms.json / COLMAP model is undistorted as a fisheye (issue 11,
defect 3), the pinhole and radial models as radial-tangential, anything else is refused by name.

Ground truth: bright dots placed at known pixels of the PINHOLE image are rendered into the fisheye photo
through cv2.fisheye's model (each fisheye pixel samples the pinhole pattern where the lens maps it); after
import and undistortion the dots must be back where the pinhole model puts them.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.capture.images import save_image
from recon.capture.scene import Frame, import_colmap, import_transforms, load_scene
from recon.errors import InputError
from recon.evaluation.views import load_view

W, H, FL = 320, 240, 200.0
K = np.array([[FL, 0, W / 2], [0, FL, H / 2], [0, 0, 1]])
FISHEYE = (0.05, -0.01, 0.002, 0.001)
DOTS = np.array([[60.0, 50.0], [260.0, 50.0], [160.0, 120.0], [60.0, 190.0], [262.0, 188.0], [110.0, 80.0]])
SIGMA = 2.5


def pinhole_pattern(px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """The scene as a pinhole camera sees it: Gaussian dots on grey, evaluated at pinhole pixel coords."""
    value = np.full(px.shape, 0.2)
    for x, y in DOTS:
        value += 0.7 * np.exp(-((px - x) ** 2 + (py - y) ** 2) / (2 * SIGMA**2))
    return value


def fisheye_photo() -> np.ndarray:
    """The photo a fisheye lens (K, FISHEYE) takes of the pinhole pattern."""
    j, i = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    # pixel centres: cv2 maps pixel coords with centres at integers, so shift by 0.5 in and out
    pts = np.stack([i - 0.5, j - 0.5], axis=-1).reshape(-1, 1, 2)
    normalized = cv2.fisheye.undistortPoints(pts, K, np.asarray(FISHEYE))
    px = normalized[:, 0, 0] * FL + W / 2 + 0.5
    py = normalized[:, 0, 1] * FL + H / 2 + 0.5
    gray = pinhole_pattern(px, py).reshape(H, W)
    return np.repeat(gray[..., None], 3, axis=-1).astype(np.float32)


def dot_centres(image: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroid of each dot, in pixel-centre coordinates, searched near its true place."""
    gray = image[..., :3].astype(np.float64).mean(axis=-1) / (255.0 if image.dtype == np.uint8 else 1.0)
    out = []
    for x, y in DOTS:
        x0, y0 = int(x) - 7, int(y) - 7
        win = np.clip(gray[y0 : y0 + 15, x0 : x0 + 15] - 0.25, 0, None)
        jj, ii = np.mgrid[y0 : y0 + 15, x0 : x0 + 15] + 0.5
        out.append([(win * ii).sum() / win.sum(), (win * jj).sum() / win.sum()])
    return np.asarray(out)


def write_capture(folder: Path, model: str, coeffs: dict) -> Path:
    (folder / "images").mkdir(parents=True)
    save_image(folder / "images" / "f0.png", fisheye_photo())
    doc = {"camera_model": model, "fl_x": FL, "fl_y": FL, "cx": W / 2, "cy": H / 2, "w": W, "h": H, **coeffs,
           "frames": [{"file_path": "images/f0.png", "transform_matrix": np.eye(4).tolist()}]}
    (folder / "transforms.json").write_text(json.dumps(doc))
    return folder


def test_pattern_is_really_distorted() -> None:
    # the fixture itself: without undistortion the off-centre dots sit pixels away from their pinhole places
    err = np.linalg.norm(dot_centres(fisheye_photo()) - DOTS, axis=1)
    assert err[2] < 0.1 and err.max() > 8.0


def test_fisheye_transforms_json_is_undistorted_as_a_fisheye(tmp_path: Path) -> None:
    capture = write_capture(tmp_path, "OPENCV_FISHEYE", dict(zip(("k1", "k2", "k3", "k4"), FISHEYE)))
    scene = import_transforms(capture)
    frame = scene.frames[0]
    assert frame.camera_model == "OPENCV_FISHEYE" and frame.distortion == FISHEYE
    view = load_view(scene, frame, max_side=W, keep_alpha=False)
    err = np.linalg.norm(dot_centres(view.image) - DOTS, axis=1)
    assert err.max() < 0.35, err
    # read as radial-tangential (what imports did before), the same coefficients leave dots far off
    wrong = load_view(scene, Frame(**{**frame.__dict__, "camera_model": "OPENCV", "k3": 0.0, "k4": 0.0}), W, False)
    assert np.linalg.norm(dot_centres(wrong.image) - DOTS, axis=1).max() > 5.0


def test_scene_json_keeps_the_lens(tmp_path: Path) -> None:
    scene = import_transforms(write_capture(tmp_path / "c", "OPENCV_FISHEYE", dict(zip(("k1", "k2", "k3", "k4"), FISHEYE))))
    (tmp_path / "s").mkdir()
    scene.save(tmp_path / "s")
    again = load_scene(tmp_path / "s").frames[0]
    assert again.camera_model == "OPENCV_FISHEYE" and again.distortion == FISHEYE


@pytest.mark.parametrize(
    ("model", "coeffs", "expected"),
    [
        ("PINHOLE", {}, (0.0, 0.0, 0.0, 0.0, 0.0)),
        ("SIMPLE_RADIAL", {"k1": 0.02}, (0.02, 0.0, 0.0, 0.0, 0.0)),
        ("RADIAL", {"k1": 0.02, "k2": -0.01}, (0.02, -0.01, 0.0, 0.0, 0.0)),
        ("OPENCV", {"k1": 0.02, "k2": -0.01, "p1": 1e-3, "p2": -1e-3, "k3": 0.004}, (0.02, -0.01, 1e-3, -1e-3, 0.004)),
    ],
)
def test_pinhole_and_radial_models_are_radial_tangential(tmp_path: Path, model: str, coeffs: dict, expected: tuple) -> None:
    frame = import_transforms(write_capture(tmp_path, model, coeffs)).frames[0]
    assert frame.camera_model == "OPENCV" and frame.distortion == pytest.approx(expected)
    # radial-tangential with k3 undistorts exactly like OpenCV's own undistort
    image = fisheye_photo()
    ours = load_view(import_transforms(tmp_path), frame, W, False).image.astype(np.float64) / 255
    ref = cv2.undistort(image, K, np.asarray(expected))
    inner = (slice(20, H - 20), slice(20, W - 20))
    assert np.abs(ours[inner] - ref[inner]).max() < 0.02


def test_unknown_transforms_camera_model_is_refused_by_name(tmp_path: Path) -> None:
    write_capture(tmp_path, "EQUIRECTANGULAR", {})
    with pytest.raises(InputError, match=r"transforms\.json.*EQUIRECTANGULAR.*OPENCV_FISHEYE"):
        import_transforms(tmp_path)


def colmap_project(folder: Path, camera_line: str) -> Path:
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "images").mkdir()
    save_image(folder / "images" / "a.png", fisheye_photo())
    (folder / "sparse" / "0" / "cameras.txt").write_text(camera_line + "\n")
    (folder / "sparse" / "0" / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (folder / "sparse" / "0" / "points3D.txt").write_text("")
    return folder


def test_colmap_fisheye_model_is_imported_as_a_fisheye(tmp_path: Path) -> None:
    params = " ".join(str(v) for v in (FL, FL, W / 2, H / 2, *FISHEYE))
    scene = import_colmap(colmap_project(tmp_path, f"1 OPENCV_FISHEYE {W} {H} {params}"))
    frame = scene.frames[0]
    assert frame.camera_model == "OPENCV_FISHEYE" and frame.distortion == pytest.approx(FISHEYE)
    err = np.linalg.norm(dot_centres(load_view(scene, frame, W, False).image) - DOTS, axis=1)
    assert err.max() < 0.35, err


def test_colmap_unsupported_model_is_refused_naming_file_and_model(tmp_path: Path) -> None:
    colmap_project(tmp_path, f"1 FOV {W} {H} {FL} {FL} {W / 2} {H / 2} 0.1")
    with pytest.raises(InputError, match=r"cameras\.txt.*FOV.*OPENCV_FISHEYE"):
        import_colmap(tmp_path)
