"""Camera math in one place: the conventions, projection, pixel rays, look-at and the OpenCV ↔ OpenGL flip.

Conventions (shared by the whole project):

* ``c2w`` is camera-to-world, OpenGL style: the camera looks down its -Z axis, +Y is up, +X right.
  OpenCV / COLMAP cameras look down +Z with +Y down; `flip_camera_axes` turns one into the other.
* Pixel (i, j) = (column, row) covers [i, i + 1) × [j, j + 1) with its centre at (i + 0.5, j + 0.5); row 0 is
  the TOP of the image.
* Intrinsics ``fl_x, fl_y, cx, cy`` are in pixels. Cameras are pinholes unless a ``distortion`` is given: OpenCV's
  radial-tangential coefficients ``(k1, k2, p1, p2[, k3])`` on normalized image coordinates (x right, y down).
  Photos are undistorted with OpenCV itself (`recon.capture.images.undistort`, fisheyes included); the numpy lens here
  serves what renders or checks distorted pixels without OpenCV (the tabletop fixture, tests).
* Ray directions are UNIT length, so a distance ``t`` along a ray is in world units: ``x = o + t * d``.
  ``z`` (depth) is the distance along the optical axis, positive in front of the camera.

Functions that torch code needs (`world_to_camera`, `project`, `pixel_centres`, `pixel_directions`, `pixel_rays`,
`image_rays`, `distort`) take numpy arrays or torch tensors and return the same kind, in the same float operation
order either way. torch is never imported here (a tensor argument means it is loaded already), so numpy-only
callers (the fixture generators, normalization) stay light. The rest (`look_at`, the OpenCV ↔ OpenGL conversions,
`intrinsic_matrix`, `pixel_footprint`) are numpy: only scene import, export and set-up code calls them.
"""
from __future__ import annotations

import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

import numpy as np

__all__ = [
    "OPENGL_TO_OPENCV",
    "distort",
    "flip_camera_axes",
    "image_rays",
    "intrinsic_matrix",
    "look_at",
    "opencv_w2c_to_opengl_c2w",
    "opengl_c2w_to_opencv_w2c",
    "pixel_centres",
    "pixel_directions",
    "pixel_footprint",
    "pixel_rays",
    "project",
    "undistort",
    "world_to_camera",
]

Array = Any
"""A numpy array or a torch tensor (the functions that accept both return the kind they are given)."""

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""(4, 4) flip of a camera's Y and Z axes: OpenGL (looks down -Z, +Y up) ↔ OpenCV (looks down +Z, +Y down).
Its own inverse; right-multiply a camera-to-world by it (`flip_camera_axes`)."""

MIN_DEPTH = 1e-12
"""`project` divides by at least this depth (in magnitude), so points on the camera's plane give finite pixels."""


# ---------------------------------------------------------------------------------------- numpy / torch dispatch
def _torch_of(x: Any) -> ModuleType | None:
    """torch when x is a tensor, else None (never imports torch: a tensor means it is loaded)."""
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(x, torch.Tensor) else None


def _stack_last(parts: Sequence[Array]) -> Array:
    torch = _torch_of(parts[0])
    return torch.stack(list(parts), dim=-1) if torch else np.stack(parts, axis=-1)


def _unit(d: Array) -> Array:
    """d (..., 3) divided by its length along the last axis."""
    torch = _torch_of(d)
    if torch:
        return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------- poses
def flip_camera_axes(pose: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world ↔ OpenCV camera-to-world (the same flip both ways): the camera's Y and Z axes negated.

    pose: (3, 3) rotation, (3, 4) or (4, 4) camera-to-world; returns the same shape (a matrix product with
    `OPENGL_TO_OPENCV`, so the centre and the world frame are unchanged)."""
    pose = np.asarray(pose)
    n = pose.shape[-1]
    return pose @ OPENGL_TO_OPENCV[:n, :n]


def opencv_w2c_to_opengl_c2w(cam_from_world: np.ndarray) -> np.ndarray:
    """World->camera [R|t] in OpenCV axes (3, 4) (COLMAP's pose) -> camera-to-world (4, 4) in OpenGL axes.

    Inverts the rigid transform exactly (R^T, -R^T t) rather than numerically, then flips the camera's Y and Z
    axes, so that the camera looks down -Z with +Y up. The world frame is unchanged. A (4, 4) is refused: it is
    more likely a camera-to-world passed by mistake than a world-to-camera.
    """
    w2c = np.asarray(cam_from_world, dtype=np.float64)
    if w2c.shape != (3, 4):
        raise ValueError(f"cam_from_world must be (3, 4), got {w2c.shape}")
    rot, trans = w2c[:, :3], w2c[:, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ trans
    return flip_camera_axes(c2w)


def opengl_c2w_to_opencv_w2c(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world (4, 4) -> world-to-camera (4, 4) in OpenCV axes (what COLMAP models store).

    A numerical inverse, so a c2w whose rotation is not exactly orthonormal (a scaled scene) still round-trips."""
    return np.linalg.inv(flip_camera_axes(np.asarray(c2w, np.float64)))


def look_at(eye: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world (4, 4) at `eye` (3,) looking at `target` (3,), level with `up` (no roll).

    Looking straight along `up` has no level heading; world +Y then stands in for up."""
    eye = np.asarray(eye, dtype=np.float64)
    back = eye - np.asarray(target, dtype=np.float64)
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:  # looking straight along `up`: any level heading will do
        right = np.cross((0.0, 1.0, 0.0), back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


# ---------------------------------------------------------------------------------------- intrinsics
def intrinsic_matrix(fl_x: float, fl_y: float, cx: float, cy: float) -> np.ndarray:
    """OpenCV's camera matrix K (3, 3) float64 of pinhole intrinsics in pixels (what cv2's lens functions take)."""
    return np.array([[fl_x, 0, cx], [0, fl_y, cy], [0, 0, 1]], dtype=np.float64)


def pixel_footprint(aabb: np.ndarray, centres: np.ndarray, focals: np.ndarray) -> tuple[float, float]:
    """World size of one training pixel at the cameras' median distance to the box centre.

    aabb: (2, 3) scene box; centres: (K, 3) camera centres (scene frame); focals: (K,) pixels.
    Returns ``(footprint, median distance)`` in scene units. Sizes the field's grids and the mesh grid.
    """
    box = np.asarray(aabb, np.float64)
    dist = float(np.median(np.linalg.norm(np.asarray(centres, np.float64) - box.mean(axis=0), axis=1)))
    return dist / float(np.median(focals)), dist


# ---------------------------------------------------------------------------------------- lens
def _lens_terms(coeffs: Sequence[float]) -> tuple[float, float, float, float, float]:
    c = [float(v) for v in coeffs]
    if not 0 <= len(c) <= 5:
        raise ValueError(f"a radial-tangential lens takes up to 5 coefficients (k1, k2, p1, p2, k3), got {len(c)}")
    k1, k2, p1, p2, k3 = c + [0.0] * (5 - len(c))
    return k1, k2, p1, p2, k3


def distort(x: Array, y: Array, coeffs: Sequence[float]) -> tuple[Array, Array]:
    """OpenCV's radial-tangential lens on normalized coordinates (x right, y down): pinhole (x, y) -> distorted.

    coeffs: (k1, k2[, p1, p2[, k3]]). x, y: arrays of one shape. Terms whose coefficient is zero are not
    evaluated, so a radial lens costs (and rounds) like x * (1 + k1 r² + k2 r⁴)."""
    k1, k2, p1, p2, k3 = _lens_terms(coeffs)
    r2 = x * x + y * y
    f = 1.0 + k1 * r2 + k2 * r2 * r2
    if k3:
        f = f + k3 * r2 * r2 * r2
    xd, yd = x * f, y * f
    if p1 or p2:
        xd = xd + (2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x))
        yd = yd + (p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, coeffs: Sequence[float], iterations: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `distort` for a radial lens (p1 = p2 = 0): Newton on the radius, numpy arrays of one shape.

    Exact where the radial map r (1 + k1 r² + k2 r⁴ + k3 r⁶) rises monotonically (a lens that can show the
    picture's corner). Tangential terms are OpenCV's business (cv2.undistortPoints): ValueError here."""
    k1, k2, p1, p2, k3 = _lens_terms(coeffs)
    if p1 or p2:
        raise ValueError("undistort inverts radial lenses only; use cv2.undistortPoints for tangential terms")
    rd = np.sqrt(xd * xd + yd * yd)
    r = rd.copy()
    for _ in range(iterations):
        r2 = r * r
        f = r * (1.0 + k1 * r2 + k2 * r2 * r2) - rd
        slope = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
        if k3:
            f = f + r * k3 * r2 * r2 * r2
            slope = slope + 7.0 * k3 * r2 * r2 * r2
        r = r - f / slope
    scale = np.where(rd > 0, r / np.maximum(rd, 1e-12), 1.0)
    return xd * scale, yd * scale


# ---------------------------------------------------------------------------------------- world -> pixels
def world_to_camera(points: Array, c2w: Array) -> Array:
    """World points (..., 3) -> the camera's own axes (..., 3) (OpenGL: in front of the camera z < 0).

    Rows times R equal R^T (p - t); c2w (4, 4) or (3, 4)."""
    return (points - c2w[:3, 3]) @ c2w[:3, :3]


def project(
    points: Array, c2w: Array, intrinsics: Sequence[float] | Array, distortion: Sequence[float] | None = None
) -> tuple[Array, Array]:
    """Project world points into an OpenGL camera.

    points: (N, 3) world (or scene) frame; c2w: (4, 4); intrinsics: (4,) fl_x, fl_y, cx, cy in pixels;
    distortion: OpenCV (k1, k2[, p1, p2[, k3]]) or None for a pinhole.
    Returns ``uv (N, 2)`` continuous pixel coordinates (x right, y down; pixel centres at +0.5) and
    ``z (N,)`` depth along the optical axis (positive in front of the camera). Points on the camera's plane
    (|z| <= MIN_DEPTH) are divided by MIN_DEPTH instead of z: finite, far outside the image, no warnings;
    callers keep ``z > 0`` (or a near limit) themselves.
    """
    cam = world_to_camera(points, c2w)
    z = -cam[..., 2]
    torch = _torch_of(z)
    safe = torch.where(z.abs() > MIN_DEPTH, z, MIN_DEPTH) if torch else np.where(np.abs(z) > MIN_DEPTH, z, MIN_DEPTH)
    fx, fy, cx, cy = intrinsics
    if distortion is None:
        u = cx + fx * cam[..., 0] / safe
        v = cy - fy * cam[..., 1] / safe
    else:
        xd, yd = distort(cam[..., 0] / safe, -cam[..., 1] / safe, distortion)
        u, v = cx + fx * xd, cy + fy * yd
    return _stack_last([u, v]), z


# ---------------------------------------------------------------------------------------- pixels -> rays
def pixel_centres(w: int, h: int, like: Array | None = None) -> tuple[Array, Array]:
    """Column and row coordinates (i + 0.5, j + 0.5) of every pixel centre, each (h, w) (image layout).

    like: a tensor to take torch, its device and dtype from; otherwise float64 numpy."""
    torch = _torch_of(like)
    if torch:
        j, i = torch.meshgrid(torch.arange(h, device=like.device, dtype=like.dtype) + 0.5,
                              torch.arange(w, device=like.device, dtype=like.dtype) + 0.5, indexing="ij")
    else:
        j, i = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    return i, j


def pixel_directions(
    px: Array, py: Array, fl_x: Any, fl_y: Any, cx: Any, cy: Any, distortion: Sequence[float] | None = None
) -> Array:
    """Camera-frame directions (..., 3) through pixel coordinates px, py (pixels, any one shape): z = -1, so they
    are NOT unit length. Image rows grow downwards while camera +Y is up, hence the sign of y.

    Intrinsics are scalars or arrays broadcasting with px (one camera per pixel). With `distortion` (a radial
    lens, see `undistort`) the pixel is undistorted first, so the ray is the one the distorted pixel sees."""
    x = (px - cx) / fl_x
    if distortion is None:
        y = -(py - cy) / fl_y
    else:
        x, y = undistort(x, (py - cy) / fl_y, distortion)
        y = -y
    torch = _torch_of(x)
    return _stack_last([x, y, -(torch.ones_like(x) if torch else np.ones_like(x))])


def pixel_rays(
    c2w: Array, fl_x: Any, fl_y: Any, cx: Any, cy: Any, px: Array, py: Array, distortion: Sequence[float] | None = None
) -> tuple[Array, Array]:
    """World rays through pixel coordinates px, py (pass ``i + 0.5``, ``j + 0.5`` for pixel centres; not offset
    here, so sub-pixel jitter is possible).

    c2w: (4, 4) or (3, 4) for one camera (px, py any one shape S), or (N, 4, 4) / (N, 3, 4) with one camera per
    ray (px, py and the intrinsics (N,)). Returns origins and unit directions, each (*S, 3) / (N, 3)."""
    d_cam = pixel_directions(px, py, fl_x, fl_y, cx, cy, distortion)
    if c2w.ndim == 3:
        torch = _torch_of(c2w)
        d = (torch or np).einsum("nij,nj->ni", c2w[:, :3, :3], d_cam)
        return c2w[:, :3, 3], _unit(d)
    d = _unit(d_cam @ c2w[:3, :3].T)
    torch = _torch_of(d)
    o = c2w[:3, 3].expand(d.shape) if torch else np.broadcast_to(c2w[:3, 3], d.shape)
    return o, d


def image_rays(c2w: Array, fl_x: Any, fl_y: Any, cx: Any, cy: Any, w: int, h: int) -> tuple[Array, Array]:
    """All rays of one pinhole image through its pixel centres: origins and unit directions, each (h, w, 3),
    ``[j, i]`` = row j, column i (the layout of an (h, w, 3) image). c2w (4, 4) or (3, 4) sets numpy or torch
    (and for torch the device and dtype)."""
    return pixel_rays(c2w, fl_x, fl_y, cx, cy, *pixel_centres(w, h, like=c2w))


MIN_KEYPOINT_ERROR_PX = 0.5
"""Floor on a sparse point's reprojection error (pixels): a keypoint's position is no better than that."""
MIN_TRIANGULATION_DEG = 1.0
"""Floor on a point's triangulation angle: a point seen along nearly one direction has a very uncertain depth."""


def triangulation_angles(points: np.ndarray, centers: np.ndarray, visible: Sequence[np.ndarray]) -> np.ndarray:
    """Widest angle (radians) between the rays from the cameras that observe each point to it.

    points (P, 3); centers (V, 3) camera centres; visible[v]: indices into points that camera v observes.
    A point observed by one camera gets 0.
    """
    pts = np.asarray(points, np.float64)
    dirs: list[list[np.ndarray]] = [[] for _ in range(len(pts))]
    for c, idx in zip(np.asarray(centers, np.float64), visible, strict=True):
        idx = np.asarray(idx, np.int64)
        d = pts[idx] - c
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        for i, di in zip(idx, d):
            dirs[i].append(di)
    angles = np.zeros(len(pts))
    for i, ds in enumerate(dirs):
        if len(ds) > 1:
            a = np.stack(ds)
            angles[i] = float(np.arccos(np.clip((a @ a.T).min(), -1.0, 1.0)))
    return angles
