"""The object of interest in a capture with background: what the cameras look at, and the ground it stands on.

Phone captures of an object show the table, the floor and the room too. The object is what every photo
keeps in frame: the sparse points that (nearly) all cameras see inside their image around the cameras'
common focus. The ground is the largest plane of sparse points roughly normal to "up" below the focus,
found by RANSAC. Pure numpy on sparse points and cameras (any frame; lengths in that frame's units).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

IN_VIEW_FRACTION = 0.8
"""A sparse point belongs to the object region when at least this fraction of the cameras has it in frame."""
GROUND_MAX_TILT_DEG = 25.0
"""The ground's normal is within this angle of the up direction."""
GROUND_MIN_FRACTION = 0.1
"""A plane counts as the ground only when at least this fraction of the sparse points lie on it."""
MIN_REGION_POINTS = 20


@dataclass
class Plane:
    """Points x with normal · x = offset; normal is unit and points up (away from the ground, toward the object)."""

    normal: np.ndarray
    offset: float
    inliers: int
    threshold: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance above the plane (N,)."""
        return np.asarray(points, np.float64) @ self.normal - self.offset


def in_view_fraction(points: np.ndarray, c2ws: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Fraction of the cameras whose image contains each point, in front of the camera. points (N, 3);
    c2ws (K, 4, 4) OpenGL; intrinsics (K, 4) fl_x, fl_y, cx, cy; sizes (K, 2) w, h (pixels)."""
    count = np.zeros(len(points))
    for c2w, (fx, fy, cx, cy), (w, h) in zip(c2ws, intrinsics, sizes, strict=True):
        local = (points - c2w[:3, 3]) @ c2w[:3, :3]
        z = -local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cx + fx * local[:, 0] / z
            v = cy - fy * local[:, 1] / z
        count += (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return count / max(len(c2ws), 1)


def fit_ground_plane(
    points: np.ndarray, up: np.ndarray, below: np.ndarray, threshold: float, background: np.ndarray | None = None,
    iterations: int = 400, seed: int = 0,
) -> Plane | None:
    """RANSAC plane through the sparse points with a normal near `up`, lying below the point `below`.

    threshold: inlier distance (scene units). background (N,) bool: the points outside the object region; a
    ground extends beyond the object, so planes are scored by their background inliers (a flat face of the
    object itself has none). The best plane is refitted to its inliers (least squares, SVD). None when no
    plane holds GROUND_MIN_FRACTION of the points.
    """
    pts = np.asarray(points, np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    weight = (np.ones(len(pts), bool) if background is None else np.asarray(background, bool))[finite]
    pts = pts[finite]
    if len(pts) < 30:
        return None
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    rng = np.random.default_rng(seed)
    cos_tilt = np.cos(np.radians(GROUND_MAX_TILT_DEG))
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < 1e-12:
            continue
        normal /= norm
        if normal @ up < 0:
            normal = -normal
        if normal @ up < cos_tilt:
            continue
        offset = float(normal @ a)
        if normal @ below - offset <= threshold:  # the ground lies under the object, not through or above it
            continue
        count = int(((np.abs(pts @ normal - offset) < threshold) & weight).sum())
        if count > best_count:
            best, best_count = (normal, offset), count
    if best is None or best_count < GROUND_MIN_FRACTION * len(pts):
        return None
    inl = pts[np.abs(pts @ best[0] - best[1]) < threshold]
    centroid = inl.mean(axis=0)
    normal = np.linalg.svd(inl - centroid, full_matrices=False)[2][2]
    if normal @ up < 0:
        normal = -normal
    offset = float(normal @ centroid)
    count = int((np.abs(pts @ normal - offset) < threshold).sum())
    return Plane(normal, offset, count, threshold)


@dataclass
class Region:
    """The object of interest: its sparse points, their box, the ground (if any) and why."""

    points: np.ndarray
    """(N,) bool: the sparse points that belong to the object."""
    ground: Plane | None
    background_fraction: float
    """Share of the sparse points outside the object region (table, floor, walls, sky)."""
    reason: str


def object_region(
    points: np.ndarray, c2ws: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray, focus: np.ndarray, up: np.ndarray
) -> Region | None:
    """The sparse points of the object the cameras look at: in frame of IN_VIEW_FRACTION of the cameras and above
    the ground plane (when one is found). None when fewer than MIN_REGION_POINTS qualify."""
    pts = np.asarray(points, np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    if finite.sum() < MIN_REGION_POINTS:
        return None
    seen = np.where(finite, in_view_fraction(np.where(finite[:, None], pts, 0.0), c2ws, intrinsics, sizes), 0.0)
    common = finite & (seen >= IN_VIEW_FRACTION)
    dist = float(np.median(np.linalg.norm(c2ws[:, :3, 3] - focus, axis=1)))
    ground = fit_ground_plane(pts, up, focus, threshold=0.01 * dist, background=~common)
    keep = common.copy()
    if ground is not None:
        keep &= ground.height(np.where(finite[:, None], pts, 0.0)) > 2 * ground.threshold
    if keep.sum() < MIN_REGION_POINTS:
        return None
    background = 1.0 - keep.sum() / finite.sum()
    why = (
        f"object of interest: the {int(keep.sum())} sparse points that at least {IN_VIEW_FRACTION:.0%} of the photos "
        f"keep in frame (around the cameras' common focus)"
    )
    if ground is not None:
        why += (f"; ground plane found by RANSAC ({ground.inliers} of {int(finite.sum())} points within "
                f"{ground.threshold:.3g} units, tilt {np.degrees(np.arccos(min(1.0, ground.normal @ up / np.linalg.norm(up)))):.1f}°): cut away")
    why += f"; {background:.0%} of the points are background"
    return Region(keep, ground, float(background), why)
