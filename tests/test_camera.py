"""The camera math (recon/camera.py): round trips between its functions, numpy against torch, against OpenCV's own
projection (an implementation that shares no code with ours), and at the extremes."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from recon.camera import (
    OPENGL_TO_OPENCV,
    distort,
    flip_camera_axes,
    image_rays,
    intrinsic_matrix,
    look_at,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_centres,
    pixel_directions,
    pixel_footprint,
    pixel_rays,
    project,
    undistort,
    world_to_camera,
)

ROOT = Path(__file__).resolve().parents[1]
INTR = np.array([310.0, 290.0, 161.3, 118.7])  # fl_x != fl_y, an off-centre principal point: no symmetry hides a swap
W, H = 320, 240
LENS = (-0.21, 0.05, 0.0012, -0.0008, 0.013)
"""k1, k2, p1, p2, k3 of a real phone-like lens (radial and tangential)."""
RADIAL = (-0.12, 0.02)


def cameras(n: int = 6, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) OpenGL c2w at random places around the origin, looking near it."""
    rng = np.random.default_rng(seed)
    return np.stack([look_at(rng.normal(size=3) * 4 + [0, 0, 1], rng.normal(size=3) * 0.3) for _ in range(n)])


def points_in_front(c2w: np.ndarray, n: int = 500, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (n, 3) inside the image at depths 0.5..20: with their pixels (n, 2) and depths (n,)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [W, H], (n, 2))
    z = rng.uniform(0.5, 20.0, n)
    x = (uv[:, 0] - INTR[2]) / INTR[0] * z
    y = -(uv[:, 1] - INTR[3]) / INTR[1] * z
    return np.stack([x, y, -z], axis=-1) @ c2w[:3, :3].T + c2w[:3, 3], uv, z


# ----------------------------------------------------------------------------- projection and rays
def test_project_puts_points_at_the_pixels_and_depths_they_were_made_for() -> None:
    for c2w in cameras():
        pts, uv, z = points_in_front(c2w)
        got_uv, got_z = project(pts, c2w, INTR)
        np.testing.assert_allclose(got_uv, uv, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got_z, z, rtol=1e-12)


def test_pixel_rays_hit_the_points_that_project_to_their_pixels() -> None:
    for c2w in cameras():
        pts, _, _ = points_in_front(c2w)
        uv, z = project(pts, c2w, INTR)
        o, d = pixel_rays(c2w, *INTR, uv[:, 0], uv[:, 1])
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, rtol=1e-14)
        t = np.einsum("ij,ij->i", pts - o, d)
        np.testing.assert_allclose(o + t[:, None] * d, pts, rtol=0, atol=1e-9 * np.abs(pts).max())
        np.testing.assert_allclose(t * -(d @ c2w[:3, 2]), z, rtol=1e-12)  # ray distance * cos = depth along the axis


def test_unproject_then_project_is_the_identity_at_every_pixel_centre() -> None:
    c2w = cameras(1)[0]
    o, d = image_rays(c2w, *INTR, W, H)
    i, j = pixel_centres(W, H)
    assert o.shape == d.shape == (H, W, 3) and i.shape == j.shape == (H, W)
    assert i[0, 0] == j[0, 0] == 0.5 and i[0, -1] == W - 0.5 and j[-1, 0] == H - 0.5  # [row, column]
    for depth in (1e-3, 1.0, 1e4):
        uv, z = project((o + depth * d).reshape(-1, 3), c2w, INTR)
        np.testing.assert_allclose(uv, np.stack([i, j], axis=-1).reshape(-1, 2), rtol=0, atol=1e-7)
        assert (z > 0).all()


def test_numpy_and_torch_give_the_same_numbers(device: torch.device) -> None:
    c2ws = cameras(3)
    pts, uv, _ = points_in_front(c2ws[0])
    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=torch.float64, device=device)

    def close(got: torch.Tensor, want: np.ndarray) -> None:
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-13, atol=1e-12)


    got_uv, got_z = project(t(pts), t(c2ws[0]), t(INTR))
    want_uv, want_z = project(pts, c2ws[0], INTR)
    close(got_uv, want_uv)
    close(got_z, want_z)
    close(world_to_camera(t(pts), t(c2ws[0])), world_to_camera(pts, c2ws[0]))
    close(pixel_directions(t(uv[:, 0]), t(uv[:, 1]), *INTR), pixel_directions(uv[:, 0], uv[:, 1], *INTR))
    close(torch.stack(distort(t(uv[:, 0] / W), t(uv[:, 1] / H), LENS)), np.stack(distort(uv[:, 0] / W, uv[:, 1] / H, LENS)))
    for got, want in zip(image_rays(t(c2ws[1]), *INTR, 16, 12), image_rays(c2ws[1], *INTR, 16, 12)):
        assert got.device.type == device.type and got.dtype == torch.float64
        close(got, want)
    idx = np.arange(len(uv)) % 3  # one camera per ray
    k = np.tile(INTR, (len(uv), 1))
    got = pixel_rays(t(c2ws[idx]), *t(k).T, t(uv[:, 0]), t(uv[:, 1]))
    want = pixel_rays(c2ws[idx], *k.T, uv[:, 0], uv[:, 1])
    for g, w in zip(got, want):
        close(g, w)
    # the batched form (one camera per ray) agrees with the one-camera form
    for c in range(3):
        o, d = pixel_rays(c2ws[c], *INTR, uv[idx == c, 0], uv[idx == c, 1])
        np.testing.assert_allclose(want[1][idx == c], d, rtol=0, atol=1e-15)
        np.testing.assert_allclose(want[0][idx == c], o, rtol=0, atol=0)


def test_torch_rays_follow_the_tensor_device_and_dtype(device: torch.device) -> None:
    c2w = torch.as_tensor(cameras(1)[0], dtype=torch.float32, device=device)
    o, d = image_rays(c2w, *INTR.tolist(), 8, 6)
    assert o.dtype == d.dtype == torch.float32 and d.device.type == device.type and d.shape == (6, 8, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(6, 8, device=device))


def test_projection_agrees_with_opencv_with_and_without_distortion() -> None:
    """cv2.projectPoints on the same camera, converted to OpenCV's convention, lands on the same pixels."""
    for c2w in cameras():
        pts, _, _ = points_in_front(c2w, n=200)
        w2c = opengl_c2w_to_opencv_w2c(c2w)
        rvec, _ = cv2.Rodrigues(w2c[:3, :3])
        for lens in (None, LENS, RADIAL):
            coeffs = np.zeros(5) if lens is None else np.array(lens + (0.0,) * (5 - len(lens)))
            ref, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], intrinsic_matrix(*INTR), coeffs)
            uv, _ = project(pts, c2w, INTR, lens)
            np.testing.assert_allclose(uv, ref.reshape(-1, 2), rtol=0, atol=1e-6)


def test_distortion_round_trip_and_distorted_pixel_rays() -> None:
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.6, 0.6, 1000), rng.uniform(-0.45, 0.45, 1000)
    for lens in (RADIAL, (RADIAL[0], RADIAL[1], 0.0, 0.0, 0.004)):
        back = undistort(*distort(x, y, lens), lens)
        np.testing.assert_allclose(np.stack(back), np.stack([x, y]), rtol=0, atol=1e-12)
    assert np.array_equal(np.stack(distort(x, y, ())), np.stack([x, y]))  # no coefficients: a pinhole
    with pytest.raises(ValueError, match="radial"):
        undistort(x, y, LENS)  # tangential terms: OpenCV's undistortPoints is the tool
    with pytest.raises(ValueError, match="coefficients"):
        distort(x, y, (0.1,) * 6)
    # a ray through a distorted pixel projects back onto that pixel through the same lens
    c2w = cameras(1)[0]
    u, v = rng.uniform(0, W, 300), rng.uniform(0, H, 300)
    o, d = pixel_rays(c2w, *INTR, u, v, distortion=RADIAL)
    uv, _ = project(o + 2.5 * d, c2w, INTR, RADIAL)
    np.testing.assert_allclose(uv, np.stack([u, v], axis=-1), rtol=0, atol=1e-8)
    pinhole, _ = project(o + 2.5 * d, c2w, INTR)
    assert np.abs(pinhole - uv).max() > 5.0  # the lens really moves the corners


# ----------------------------------------------------------------------------- poses
def test_look_at_puts_its_target_on_the_principal_point_level_and_upright() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        eye, target = rng.normal(size=3) * 5, rng.normal(size=3)
        c2w = look_at(eye, target)
        np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)  # rotation, right-handed
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
        uv, z = project(target[None], c2w, INTR)
        np.testing.assert_allclose(uv[0], INTR[2:], rtol=0, atol=1e-9)
        assert z[0] == pytest.approx(np.linalg.norm(eye - target))
        assert abs(c2w[2, 0]) < 1e-12 and c2w[2, 1] >= 0  # no roll: camera +X level, +Y toward world +Z
    down = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3))  # straight along `up`: still a valid camera
    assert np.isfinite(down).all() and np.allclose(down[:3, :3].T @ down[:3, :3], np.eye(3))
    np.testing.assert_allclose(project(np.zeros((1, 3)), down, INTR)[0][0], INTR[2:], atol=1e-12)


def test_opencv_opengl_conversions_round_trip_and_keep_what_the_camera_sees() -> None:
    for c2w in cameras():
        w2c_cv = opengl_c2w_to_opencv_w2c(c2w)
        assert np.array_equal(w2c_cv[3], [0, 0, 0, 1])
        np.testing.assert_allclose(opencv_w2c_to_opengl_c2w(w2c_cv[:3]), c2w, rtol=0, atol=1e-12)  # COLMAP's (3, 4)
        np.testing.assert_allclose(opengl_c2w_to_opencv_w2c(opencv_w2c_to_opengl_c2w(w2c_cv[:3])), w2c_cv, atol=1e-12)
        assert np.array_equal(flip_camera_axes(flip_camera_axes(c2w)), c2w)  # its own inverse, exactly
        assert np.array_equal(flip_camera_axes(c2w[:3, :3]), (c2w @ OPENGL_TO_OPENCV)[:3, :3])  # rotations too
        # an OpenCV camera sees a point in front (+Z) at fx x / z + cx, fy y / z + cy: the same pixel
        pts, uv, z = points_in_front(c2w, n=50)
        cam = pts @ w2c_cv[:3, :3].T + w2c_cv[:3, 3]
        np.testing.assert_allclose(cam[:, 2], z, rtol=1e-12)
        np.testing.assert_allclose(cam[:, :2] / cam[:, 2:] @ np.diag(INTR[:2]) + INTR[2:], uv, atol=1e-9)
        np.testing.assert_allclose(flip_camera_axes(c2w)[:3, 3], c2w[:3, 3])  # the centre stays
    for wrong in (np.eye(3), np.eye(4)):  # a (4, 4) is more likely a c2w passed by mistake
        with pytest.raises(ValueError, match="cam_from_world"):
            opencv_w2c_to_opengl_c2w(wrong)


def test_intrinsic_matrix_and_pixel_footprint_closed_forms() -> None:
    k = intrinsic_matrix(*INTR)
    assert k.dtype == np.float64 and np.array_equal(k, [[INTR[0], 0, INTR[2]], [0, INTR[1], INTR[3]], [0, 0, 1]])
    centres = np.array([[4.0, 0, 0], [0, 4.0, 0], [0, 0, -4.0]])
    fp, dist = pixel_footprint(np.array([[-1.0, -1, -1], [1, 1, 1]]), centres, np.array([400.0, 400.0, 400.0]))
    assert dist == pytest.approx(4.0) and fp == pytest.approx(0.01)


# ----------------------------------------------------------------------------- extremes
def test_points_behind_on_the_plane_of_and_on_the_axis_of_the_camera() -> None:
    c2w = cameras(1)[0]
    axis = -c2w[:3, 2]  # the viewing direction
    right = c2w[:3, 0]
    pts = c2w[:3, 3] + np.array([2.0 * axis, -2.0 * axis, 1e-15 * axis + right, np.zeros(3), 0.5 * right])
    with np.errstate(all="raise"):  # no division warnings
        uv, z = project(pts, c2w, INTR)
    assert np.isfinite(uv).all()
    np.testing.assert_allclose(uv[0], INTR[2:], rtol=0, atol=1e-12)  # on the axis: the principal point
    assert z[0] == pytest.approx(2.0) and z[1] == pytest.approx(-2.0)  # behind the camera: negative depth
    np.testing.assert_allclose(uv[1], INTR[2:], rtol=0, atol=1e-12)  # behind, on the axis: still the centre
    assert (z[2:] <= 1e-12).all() and np.abs(uv[[2, 4], 0]).min() > 1e6  # on the camera's plane: far off the image
    # a point behind the camera mirrors through the centre: callers must test z > 0 themselves
    side = c2w[:3, 3] + 2.0 * axis + 0.3 * right
    behind = c2w[:3, 3] - 2.0 * axis - 0.3 * right
    mirrored, _ = project(np.stack([side, behind]), c2w, INTR)
    np.testing.assert_allclose(mirrored[0], mirrored[1], rtol=0, atol=1e-9)


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e6])
def test_projection_and_rays_do_not_depend_on_the_scene_scale(scale: float) -> None:
    c2w = cameras(1)[0]
    pts, uv, z = points_in_front(c2w)
    scaled = c2w.copy()
    scaled[:3, 3] *= scale
    got_uv, got_z = project(pts * scale, scaled, INTR)
    np.testing.assert_allclose(got_uv, uv, rtol=0, atol=1e-7)
    np.testing.assert_allclose(got_z, z * scale, rtol=1e-9)
    o, d = pixel_rays(scaled, *INTR, uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(o + (z * scale / -(d @ c2w[:3, 2]))[:, None] * d, pts * scale, rtol=1e-8,
                               atol=1e-8 * scale)


# ----------------------------------------------------------------------------- the module itself
def test_camera_module_imports_only_numpy_and_never_loads_torch() -> None:
    tree = ast.parse((ROOT / "recon" / "camera.py").read_text(encoding="utf-8"))
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module}
    assert imported <= {"__future__", "collections", "numpy", "sys", "types", "typing"}, imported
    code = "import sys, numpy as np, recon.camera as c; c.project(np.zeros((1, 3)), np.eye(4), [1, 1, 0, 0]); " \
           "c.image_rays(np.eye(4), 1, 1, 0, 0, 2, 2); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"  # the fixture generators and normalization stay torch-free
