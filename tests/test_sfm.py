"""Structure from motion: pose/intrinsics conversions against closed forms, then pycolmap end to end.

End-to-end checks compare recovered camera-to-world poses with true (synthetic) or reference (fox)
poses after the best similarity alignment (Umeyama on camera centres): median centre error as a
fraction of the cameras' RMS radius around their centroid, and median rotation error in degrees.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from recon.colmap import camera_params_to_intrinsics, opencv_w2c_to_opengl_c2w
from recon.errors import ReconError
from recon.sfm import (
    SfmOptions,
    SfmResult,
    choose_camera,
    run_sfm,
)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation from a random unit quaternion."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |dst - (s R src + t)|^2; src, dst: (N, 3) (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1.0
    rot = u @ e @ vt
    scale = float(np.trace(np.diag(sig) @ e) / (xs**2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def pose_errors(est: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> tuple[float, float, int]:
    """(median centre error / RMS camera radius, median rotation error in degrees, frames compared)."""
    names = sorted(set(est) & set(ref))
    e = np.stack([est[n] for n in names])
    r = np.stack([ref[n] for n in names])
    s, rot, t = umeyama(e[:, :3, 3], r[:, :3, 3])
    centres = s * e[:, :3, 3] @ rot.T + t
    radius = np.sqrt(((r[:, :3, 3] - r[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    pos = np.linalg.norm(centres - r[:, :3, 3], axis=1) / radius
    rel = np.einsum("nji,jk,nkl->nil", r[:, :3, :3], rot, e[:, :3, :3])  # R_ref^T R_align R_est
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.median(pos)), float(np.median(ang)), len(names)


def reference_poses(transforms: Path) -> dict[str, np.ndarray]:
    """image file name -> (4, 4) c2w from a transforms.json."""
    data = json.loads(transforms.read_text())
    return {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], float) for f in data["frames"]}


def estimated_poses(result: SfmResult) -> dict[str, np.ndarray]:
    return {name: np.asarray(frame["c2w"]) for name, frame in result.frames.items()}


def downsize(src: Path, dst: Path, max_side: int) -> list[str]:
    """Copies the JPEGs of src into dst with the longer side at most max_side px; returns names."""
    dst.mkdir(parents=True, exist_ok=True)
    names = sorted(p.name for p in src.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    for name in names:
        with Image.open(src / name) as im:
            im = im.convert("RGB")
            im.thumbnail((max_side, max_side), Image.Resampling.LANCZOS)
            im.save(dst / name, quality=95)
    return names


def check_result_consistency(result: SfmResult, names: list[str]) -> None:
    """Invariants every result must satisfy, whatever the data."""
    assert sorted(result.registered + result.dropped) == sorted(names)
    assert set(result.frames) == set(result.registered)
    for frame in result.frames.values():
        c2w = np.asarray(frame["c2w"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_array_equal(c2w[3], [0, 0, 0, 1])
        assert 0 < frame["cx"] < frame["w"] and 0 < frame["cy"] < frame["h"]
    p = result.num_points
    assert result.points_xyz.shape == (p, 3) and result.points_rgb.shape == (p, 3)
    assert result.points_rgb.dtype == np.uint8 and result.points_error.shape == (p,)
    assert set(result.points_visible) == set(result.registered)
    for name, idx in result.points_visible.items():
        assert idx.size > 0 and idx.min() >= 0 and idx.max() < p, name
    # every sparse point lies in front of (OpenGL: at negative camera z) the cameras that see it
    for name, idx in result.points_visible.items():
        c2w = np.asarray(result.frames[name]["c2w"])
        z_cam = (result.points_xyz[idx] - c2w[:3, 3]) @ c2w[:3, 2]
        assert np.mean(z_cam < 0) > 0.99, name


# ----------------------------------------------------------------------------------------------
# conversions (closed forms)
# ----------------------------------------------------------------------------------------------
def test_w2c_opencv_to_c2w_opengl_inverts_and_flips_axes() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        rot_gl, centre = random_rotation(rng), rng.normal(size=3) * 5
        c2w_gl = np.eye(4)
        c2w_gl[:3, :3], c2w_gl[:3, 3] = rot_gl, centre
        # the same camera in OpenCV axes: x right, y down, z forward
        c2w_cv = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])
        w2c_cv = np.linalg.inv(c2w_cv)[:3]
        np.testing.assert_allclose(opencv_w2c_to_opengl_c2w(w2c_cv), c2w_gl, atol=1e-12)


def test_w2c_conversion_point_in_front_projects_forward() -> None:
    # COLMAP camera at the world origin looking down world +Z (identity pose), point at z = 2
    c2w = opencv_w2c_to_opengl_c2w(np.hstack([np.eye(3), np.zeros((3, 1))]))
    point = np.array([0.1, 0.2, 2.0])
    cam = c2w[:3, :3].T @ (point - c2w[:3, 3])
    assert cam[2] == pytest.approx(-2.0)  # OpenGL: in front means negative z
    assert cam[1] == pytest.approx(-0.2)  # image-down (OpenCV +y) is OpenGL -y
    assert cam[0] == pytest.approx(0.1)
    # camera centre of a translated COLMAP pose is -R^T t
    rot = random_rotation(np.random.default_rng(1))
    t = np.array([0.5, -1.0, 3.0])
    c2w = opencv_w2c_to_opengl_c2w(np.hstack([rot, t[:, None]]))
    np.testing.assert_allclose(c2w[:3, 3], -rot.T @ t, atol=1e-12)
    with pytest.raises(ValueError):
        opencv_w2c_to_opengl_c2w(np.eye(4))


@pytest.mark.parametrize(
    ("model", "params", "expected"),
    [
        ("SIMPLE_PINHOLE", [500, 320, 240], dict(fl_x=500, fl_y=500, cx=320, cy=240)),
        ("PINHOLE", [500, 510, 320, 240], dict(fl_x=500, fl_y=510, cx=320, cy=240)),
        ("SIMPLE_RADIAL", [500, 320, 240, 0.01], dict(fl_x=500, fl_y=500, cx=320, cy=240, k1=0.01)),
        ("RADIAL", [500, 320, 240, 0.01, -0.002], dict(fl_x=500, fl_y=500, cx=320, cy=240, k1=0.01, k2=-0.002)),
        (
            "OPENCV",
            [500, 510, 320, 240, 0.01, -0.002, 1e-4, -2e-4],
            dict(fl_x=500, fl_y=510, cx=320, cy=240, k1=0.01, k2=-0.002, p1=1e-4, p2=-2e-4),
        ),
    ],
)
def test_camera_params_to_intrinsics(model: str, params: list[float], expected: dict[str, float]) -> None:
    full = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0, "k4": 0.0, **expected}
    assert camera_params_to_intrinsics(model, np.asarray(params, float)) == pytest.approx(full)


def test_camera_params_rejects_unknown_model_and_wrong_count() -> None:
    with pytest.raises(ValueError, match="FULL_OPENCV"):
        camera_params_to_intrinsics("FULL_OPENCV", np.zeros(12))
    with pytest.raises(ValueError, match="takes 4"):
        camera_params_to_intrinsics("SIMPLE_RADIAL", np.zeros(3))


def test_choose_camera_auto_shares_only_one_size_and_device() -> None:
    model, shared, reason = choose_camera([(400, 300)] * 5, [None] * 5)
    assert (model, shared) == ("SIMPLE_RADIAL", True)
    assert "400x300" in reason and "shared" in reason
    model, shared, reason = choose_camera([(400, 300)] * 4 + [(300, 400)], [None] * 5)
    assert not shared and "2 sizes" in reason
    _, shared, reason = choose_camera([(400, 300)] * 3, ["Pixel 7", "Pixel 7", "iPhone 13"])
    assert not shared and "2 cameras" in reason
    _, shared, reason = choose_camera([(400, 300)] * 3, ["Pixel 7"] * 3)
    assert shared and "Pixel 7" in reason
    model, shared, _ = choose_camera([(400, 300)] * 3, [None] * 3, "OPENCV", "no")
    assert (model, shared) == ("OPENCV", False)
    with pytest.raises(ReconError, match="one size"):
        choose_camera([(400, 300), (300, 400)], [None, None], shared_intrinsics="yes")
    with pytest.raises(ValueError):
        choose_camera([(400, 300)], [None], camera_model="FISHEYE")


# ----------------------------------------------------------------------------------------------
# end to end
# ----------------------------------------------------------------------------------------------
def test_synthetic_capture_recovers_true_poses(tmp_path: Path) -> None:
    from fixtures.generate import generate

    # 30 views at 320 px is about the sparsest capture of this texture where every view registers
    # (20 at 240 px gets a few hundred features per view and breaks apart); ~8 s render + ~10 s SfM
    capture = generate(tmp_path / "capture", scene="blocks", views=30, size=320, seed=0,
                       supersample=1, mesh_res=32, mesh_faces=None)
    names = sorted(p.name for p in (capture / "images").iterdir())
    phases: list[tuple[str, float]] = []
    result = run_sfm(capture / "images", names, tmp_path / "work", SfmOptions(),
                     progress=lambda phase, fraction: phases.append((phase, fraction)))

    assert len(result.registered) >= len(names) - 1, result.dropped
    check_result_consistency(result, names)
    pos, rot, count = pose_errors(estimated_poses(result), reference_poses(capture / "transforms.json"))
    assert count == len(result.registered)
    assert pos <= 0.01 and rot <= 1.0, (pos, rot)
    # the true camera is a pinhole with f = 0.5 w / tan(22.5 deg); SIMPLE_RADIAL trades focal length for a
    # small k1 when the object fills only the image centre, and squared-error bundle adjustment lets a few
    # off matches pull it (-1.6 % on this capture); the final Cauchy-loss adjustment brought it to -0.6 %
    truth = json.loads((capture / "transforms.json").read_text())
    focal = np.median([f["fl_x"] for f in result.frames.values()])
    assert focal == pytest.approx(truth["fl_x"], rel=0.012)
    ref = result.refinement
    assert ref["loss"] == "cauchy" and ref["focal_after"] == pytest.approx(focal)
    assert ref["error_after_px"] <= ref["error_before_px"]  # the robust fit discounts the off matches
    assert result.mean_reprojection_error < 1.0
    assert result.camera_model == "SIMPLE_RADIAL" and result.shared_intrinsics
    assert {p for p, _ in phases} == {"extract", "match", "map"} and ("map", 1.0) in phases
    assert set(result.timings) == {"extract", "match", "map"}
    assert (tmp_path / "work" / "database.db").is_file()
    assert (tmp_path / "work" / "sparse" / "cameras.bin").is_file()


def test_too_few_photos_raise_recon_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    for i in range(2):
        Image.fromarray(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)).save(tmp_path / f"{i}.png")
    with pytest.raises(ReconError, match="at least 3 photos"):
        run_sfm(tmp_path, ["0.png", "1.png"], tmp_path / "work", SfmOptions())


def test_unrelated_photos_raise_recon_error(tmp_path: Path) -> None:
    """Noise images share no scene: nothing (or nearly nothing) registers, and the message says why."""
    rng = np.random.default_rng(0)
    names = []
    for i in range(6):
        coarse = rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)  # blobs: SIFT finds features
        img = Image.fromarray(coarse).resize((200, 200), Image.Resampling.BICUBIC)
        names.append(f"noise_{i}.png")
        img.save(tmp_path / names[-1])
    with pytest.raises(ReconError) as info:
        run_sfm(tmp_path, names, tmp_path / "work", SfmOptions())
    message = str(info.value)
    assert "of 6 photos" in message and "overlap" in message and "texture" in message
    assert "sharper" in message and "more photos" in message


@pytest.mark.slow  # 36 s alone on 2 cores, 100 s when the machine is busy
def test_fox_matches_reference_poses(shared_data: Path, tmp_path: Path) -> None:
    """67 real phone photos at 400 px: nearly all register, poses agree with instant-ngp's COLMAP run."""
    fox = shared_data / "fox"
    names = downsize(fox / "images", tmp_path / "images", 400)
    start = time.perf_counter()
    result = run_sfm(tmp_path / "images", names, tmp_path / "work", SfmOptions(matcher="exhaustive"))
    elapsed = time.perf_counter() - start
    assert len(result.registered) >= 64, result.dropped
    check_result_consistency(result, names)
    pos, rot, _ = pose_errors(estimated_poses(result), reference_poses(fox / "transforms.json"))
    print(f"fox: {len(result.registered)}/67 in {elapsed:.0f} s, position {pos:.2%}, rotation {rot:.2f} deg")
    assert pos <= 0.01 and rot <= 1.0, (pos, rot)
    # reference focal 1375.5 px at 1080 px wide, here 225 px wide
    assert result.frames[result.registered[0]]["fl_x"] == pytest.approx(1375.52 * 225 / 1080, rel=0.03)


@pytest.mark.slow  # ~45 s on a busy 2-core machine
def test_sceaux_castle_registers_all(shared_data: Path, tmp_path: Path) -> None:
    """11 photos of a facade at 800 px: all register; focal length agrees with the supplied K."""
    names = downsize(shared_data / "sceaux_castle" / "images", tmp_path / "images", 800)
    assert len(names) == 11
    start = time.perf_counter()
    result = run_sfm(tmp_path / "images", names, tmp_path / "work", SfmOptions())
    print(f"sceaux: {len(result.registered)}/11 in {time.perf_counter() - start:.0f} s {result.timings}")
    assert result.registered == names, result.dropped
    check_result_consistency(result, names)
    frame = result.frames[names[0]]
    scale = frame["w"] / 2832
    assert frame["fl_x"] == pytest.approx(2905.88 * scale, rel=0.05)
    assert math.isfinite(result.mean_reprojection_error) and result.mean_reprojection_error < 1.5
