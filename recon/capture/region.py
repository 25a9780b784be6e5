"""The object of interest in a capture with background: what the cameras look at, and the ground it stands on.

Phone captures of an object show the table, the floor and the room too. The object is what every photo keeps in
frame: the sparse points that (nearly) all cameras see inside their image around the cameras' common focus, less the
groups of them apart that the photos frame off to the side (a cup or a book beside it, photographed from further
back), and the points linked to them off the support (close-ups leave an object's ends out of frame). The ground is
the largest plane of sparse points roughly normal to "up" below the focus, found by RANSAC; an object with no ground
under it may hang on a wall (a mounted head, a picture, a relief): then the support is the largest plane that every
camera faces and the object stands out from, and what it hangs on (a plaque, a board) belongs to it though its plain
faces give too few points to link. Numpy (and scipy's k-d tree) on sparse points and cameras (any frame; lengths in
that frame's units).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from recon.camera import project

IN_VIEW_FRACTION = 0.8
"""A sparse point belongs to the object region when at least this fraction of the cameras has it in frame."""
GROUND_MAX_TILT_DEG = 25.0
"""The ground's normal is within this angle of the up direction."""
GROUND_MIN_FRACTION = 0.1
"""A plane counts as the ground (or a wall) only when at least this fraction of the sparse points lie on it."""
WALL_MAX_BEHIND = 0.05
"""A wall has at most this fraction of the object region's points behind it (the rest on it or in front)."""
MIN_REGION_POINTS = 20
AIM_MAX = 0.5
"""The photos aim at the object: of the groups the region's points fall into (`linked_groups`), only those whose
point nearest the photo's centre lies within this fraction of the way from the centre to the frame's edge, in the
median photo, belong to it. A book or a cup on the table beside a small object photographed from further back is in
frame of nearly every photo too, but off to the side (benchmarks/results/far_tabletop.json)."""
LINK_SPACINGS = 6.0
"""Points above the support closer than this many times the median spacing of the region's points are linked: the
object is the region's points and every point linked to them, so the parts of it that close-ups leave out of frame
(a head's ears and snout, a long handle) belong to it too (the stray-point link of `recon.capture.normalization`)."""
MAX_GROWTH = 0.5
"""... up to this fraction of the region's size beyond its box on each side: an object that touches a wall or a
shelf must not make the room the object."""
MOUNT_IN_VIEW_FRACTION = 0.6
"""What an object on a wall hangs on (`mounted_points`) shows beside it: at least this fraction of the photos (framed on
the object, `IN_VIEW_FRACTION`) keep it in frame; the room beside the object leaves most close photos' frames."""
MOUNT_MIN_POINTS = 5
"""A mount is a surface: SfM places at least this many points on it; fewer are stray triangulations between the wall
and the object, which would grow the region to the wall (benchmarks/results/fox_fast_mount.json)."""
MOUNT_GAP_SPACINGS = 2.0
"""Wall shows between a point and the object (so the point is no part of its mount) when a wall point lies within
this many times the wall points' median spacing of the line between them, seen along the wall's normal."""
MOUNT_GAP_SAMPLES = 512
"""... tested at most at this many places along the line (a denser wall widens the test instead)."""


@dataclass
class Plane:
    """Points x with normal · x = offset; normal is unit and points away from the support, toward the object
    (up for the ground, toward the cameras for a wall)."""

    normal: np.ndarray
    offset: float
    inliers: int
    threshold: float
    kind: str = "ground"
    """"ground" (under the object) or "wall" (behind it)."""

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance above the plane (N,)."""
        return np.asarray(points, np.float64) @ self.normal - self.offset


def in_view_fraction(points: np.ndarray, c2ws: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Fraction of the cameras whose image contains each point, in front of the camera. points (N, 3);
    c2ws (K, 4, 4) OpenGL; intrinsics (K, 4) fl_x, fl_y, cx, cy; sizes (K, 2) w, h (pixels)."""
    count = np.zeros(len(points))
    for c2w, intr, (w, h) in zip(c2ws, intrinsics, sizes, strict=True):
        uv, z = project(points, c2w, intr)
        count += (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return count / max(len(c2ws), 1)


def fit_ground_plane(
    points: np.ndarray, up: np.ndarray, below: np.ndarray, threshold: float, background: np.ndarray | None = None,
    iterations: int = 400, seed: int = 0,
) -> Plane | None:
    """RANSAC plane through the sparse points with a normal near `up`, lying below the point `below`.

    threshold: inlier distance (scene units). background (N,) bool: the points outside the object region; a
    ground extends beyond the object, so planes are scored by their background inliers (a flat face of the
    object itself has none). The best plane is refitted to its inliers (least squares, SVD). None when no
    plane holds GROUND_MIN_FRACTION of the points; where no plane's background points do (the table of photos
    taken from further back is in nearly every frame), the plane holding most points, if GROUND_MIN_FRACTION of
    the background points (and MIN_REGION_POINTS) lie on it too.
    """
    pts = np.asarray(points, np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    weight = (np.ones(len(pts), bool) if background is None else np.asarray(background, bool))[finite]
    pts = pts[finite]
    if len(pts) < 30:
        return None
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    cos_tilt = np.cos(np.radians(GROUND_MAX_TILT_DEG))

    def under_object(normal: np.ndarray, offset: float) -> bool:  # near up, under the object, not through or above it
        return normal @ up >= cos_tilt and normal @ below - offset > threshold

    best = _ransac_plane(pts, up, weight, threshold, under_object, iterations, seed)
    if best is None and background is not None:
        # photos from further back keep most of the table in nearly every frame, so few of its points are background:
        # score every point then, and take the plane only where it holds background points too (it reaches beyond
        # the object's region, which a flat face of the object does not)
        best = _ransac_plane(pts, up, np.ones(len(pts), bool), threshold, under_object, iterations, seed)
        if best is not None:
            beyond = int(((np.abs(pts @ best[0] - best[1]) < threshold) & weight).sum())
            if beyond < max(MIN_REGION_POINTS, GROUND_MIN_FRACTION * weight.sum()):
                best = None
    return None if best is None else Plane(*best, threshold)


def _ransac_plane(
    pts: np.ndarray, toward: np.ndarray, weight: np.ndarray, threshold: float,
    accept: Callable[[np.ndarray, float], bool], iterations: int, seed: int,
) -> tuple[np.ndarray, float, int] | None:
    """RANSAC: of the planes through three random points (normal turned toward ``toward``) that ``accept(normal,
    offset)`` allows, the one with the most ``weight`` points within threshold, refit to all its inliers: (normal,
    offset, points within threshold of the refit). None when that best count is under GROUND_MIN_FRACTION of the
    points."""
    rng = np.random.default_rng(seed)
    best, best_count = None, 0
    for _ in range(iterations):
        a, b, c = pts[rng.choice(len(pts), 3, replace=False)]
        normal = np.cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < 1e-12:
            continue
        normal /= norm
        if normal @ toward < 0:
            normal = -normal
        offset = float(normal @ a)
        if not accept(normal, offset):
            continue
        count = int(((np.abs(pts @ normal - offset) < threshold) & weight).sum())
        if count > best_count:
            best, best_count = (normal, offset), count
    if best is None or best_count < GROUND_MIN_FRACTION * len(pts):
        return None
    normal, offset = _refit(pts, *best, threshold)
    return normal, offset, int((np.abs(pts @ normal - offset) < threshold).sum())


def _refit(pts: np.ndarray, normal: np.ndarray, offset: float, threshold: float) -> tuple[np.ndarray, float]:
    """Least-squares (SVD) plane through the inliers of (normal, offset), its normal on the same side."""
    inl = pts[np.abs(pts @ normal - offset) < threshold]
    centroid = inl.mean(axis=0)
    refit = np.linalg.svd(inl - centroid, full_matrices=False)[2][2]
    if refit @ normal < 0:
        refit = -refit
    return refit, float(refit @ centroid)


def support_kind(normal: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> str:
    """"ground" for a plane whose normal (its first three values) is within GROUND_MAX_TILT_DEG of up, else "wall"."""
    n, u = np.asarray(normal, np.float64)[:3], np.asarray(up, np.float64)
    cos = float(n @ u / (np.linalg.norm(n) * np.linalg.norm(u)))
    return "ground" if cos >= np.cos(np.radians(GROUND_MAX_TILT_DEG)) else "wall"


def fit_wall_plane(
    points: np.ndarray, cameras: np.ndarray, common: np.ndarray, threshold: float, iterations: int = 1000, seed: int = 0,
) -> Plane | None:
    """RANSAC plane of a wall the object hangs on: every camera (centres (K, 3)) in front of it, at most
    WALL_MAX_BEHIND of the object region's points (``common`` (N,) bool) behind it, and scored, like the ground,
    by the points outside the region on it (a wall extends beyond the object; a flat face of the object does not).

    On the fox (a mounted head) it finds the wallpapered wall, the picture frame above the head on it too (the
    region's `reason` says how many points lie on it). The normal points toward the cameras. None when no plane
    holds GROUND_MIN_FRACTION of the points, or when the cameras surround the object (no plane has them all in front
    and the object's points on its front side).
    """
    pts = np.asarray(points, np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    common = np.asarray(common, bool)[finite]
    pts = pts[finite]
    cams = np.asarray(cameras, np.float64).reshape(-1, 3)
    if len(pts) < 30 or not common.any():
        return None
    toward = np.median(cams, axis=0) - np.median(pts[common], axis=0)
    on_region = pts[common]

    def behind_object(normal: np.ndarray, offset: float) -> bool:  # every camera in front, the object on or before it
        return bool(np.all(cams @ normal - offset > threshold)
                    and np.mean(on_region @ normal - offset < -threshold) <= WALL_MAX_BEHIND)

    best = _ransac_plane(pts, toward, ~common, threshold, behind_object, iterations, seed)
    return None if best is None else Plane(*best, threshold, kind="wall")


@dataclass
class Region:
    """The object of interest: its sparse points, their box, the ground (if any) and why."""

    points: np.ndarray
    """(N,) bool: the sparse points that belong to the object."""
    ground: Plane | None
    background_fraction: float
    """Share of the sparse points outside the object region (table, floor, walls, sky)."""
    reason: str
    mount: np.ndarray
    """(N,) bool: the object's points that are what it hangs on (`mounted_points`); too few and apart to survive a
    stray-point filter, so a box of the object holds them as they are."""
    aside: np.ndarray
    """(N,) bool: the points in frame as often as the object's but in groups the photos frame off to the side
    (`aimed_groups`): things beside the object, background to its masks even where they lie inside its box."""


def object_region(
    points: np.ndarray, c2ws: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray, focus: np.ndarray, up: np.ndarray,
    leave_aside: bool = True,
) -> Region | None:
    """The sparse points of the object the cameras look at: in frame of IN_VIEW_FRACTION of the cameras and above
    the ground plane, or in front of the wall when there is no ground (when one is found), in the groups the photos
    aim at (`aimed_groups`; all of them unless `leave_aside`), and those linked to them there (`linked_points`). None
    when fewer than MIN_REGION_POINTS qualify."""
    pts = np.asarray(points, np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    if finite.sum() < MIN_REGION_POINTS:
        return None
    seen = np.where(finite, in_view_fraction(np.where(finite[:, None], pts, 0.0), c2ws, intrinsics, sizes), 0.0)
    common = finite & (seen >= IN_VIEW_FRACTION)
    dist = float(np.median(np.linalg.norm(c2ws[:, :3, 3] - focus, axis=1)))
    ground = fit_ground_plane(pts, up, focus, threshold=0.01 * dist, background=~common)
    if ground is None:
        ground = fit_wall_plane(pts, c2ws[:, :3, 3], common, threshold=0.01 * dist)
    off_support = finite.copy()
    if ground is not None:
        off_support &= ground.height(np.where(finite[:, None], pts, 0.0)) > 2 * ground.threshold
    keep = common & off_support
    if keep.sum() < MIN_REGION_POINTS:
        return None
    aimed, groups_aside = aimed_groups(pts, keep, c2ws, intrinsics, sizes) if leave_aside else (keep, 0)
    aside, keep = keep & ~aimed, aimed
    if keep.sum() < MIN_REGION_POINTS:
        return None
    in_frame = int(keep.sum())
    keep = linked_points(pts, keep, off_support & ~aside)  # what the photos frame off to the side is no part of it
    linked = int(keep.sum())
    mount = np.zeros_like(keep)
    if ground is not None and ground.kind == "wall":
        mount = mounted_points(pts, keep, off_support & (seen >= MOUNT_IN_VIEW_FRACTION), ground)
        keep |= mount
    background = 1.0 - keep.sum() / finite.sum()
    why = (
        f"object of interest: the {in_frame} sparse points that at least {IN_VIEW_FRACTION:.0%} of the photos "
        f"keep in frame (around the cameras' common focus)"
    )
    if linked > in_frame:
        why += f" and the {linked - in_frame} linked to them that fewer photos show"
    if keep.sum() > linked:
        why += (f", and the {int(keep.sum()) - linked} that stand off the wall behind it and beside it: what it is "
                f"mounted on (a board, a plaque), too plain for SfM to place enough points on to link")
    if aside.any():
        why += (f"; {int(aside.sum())} more in frame of as many photos but apart from them, in {groups_aside} group(s) "
                f"that the photos frame off to the side (stray matches, or things beside the object such as a cup or a "
                f"book): left out (normalize.beside=keep keeps them)")
    if ground is not None:
        tilt = np.degrees(np.arccos(np.clip(ground.normal @ up / np.linalg.norm(up), -1.0, 1.0)))
        what = ("ground plane" if ground.kind == "ground" else
                "no ground under the object, but a wall behind it that every photo faces")
        why += (f"; {what} found by RANSAC ({ground.inliers} of {int(finite.sum())} points within "
                f"{ground.threshold:.3g} units, tilt {tilt:.1f}° from up): cut away")
    why += f"; {background:.0%} of the points are background"
    return Region(keep, ground, float(background), why, mount, aside)


def aimed_groups(
    points: np.ndarray, seeds: np.ndarray, c2ws: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray
) -> tuple[np.ndarray, int]:
    """The seed points (N,) bool in the groups the photos aim at (`AIM_MAX`; groups: links shorter than LINK_SPACINGS
    times the seeds' median spacing chain) and the number of groups left out. All are kept when the seeds form one
    group or none of them is aimed at (nothing to tell the object from)."""
    seeds = np.asarray(seeds, bool)
    index = np.flatnonzero(seeds)
    spacing = median_spacing(points[index])
    if spacing <= 0:
        return seeds.copy(), 0
    label = linked_groups(points[index], LINK_SPACINGS * spacing)
    count = int(label.max()) + 1
    if count == 1:
        return seeds.copy(), 0
    nearest = np.full((len(c2ws), count), np.inf)  # per photo and group: its point nearest the photo's centre
    for k, (c2w, intr, (w, h)) in enumerate(zip(c2ws, intrinsics, sizes, strict=True)):
        uv, z = project(points[index], c2w, intr)
        off = np.where(z > 0, np.hypot((uv[:, 0] - w / 2) / (w / 2), (uv[:, 1] - h / 2) / (h / 2)), np.inf)
        np.minimum.at(nearest[k], label, off)
    aim = np.median(nearest, axis=0)
    aimed = aim <= AIM_MAX
    if not aimed.any():
        return seeds.copy(), 0
    out = seeds.copy()
    out[index[~aimed[label]]] = False
    return out, int((~aimed).sum())


def linked_points(points: np.ndarray, seeds: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """(N,) bool: the seed points and the candidate points linked to them by chains of links shorter than
    LINK_SPACINGS times the seeds' median nearest-neighbour spacing, within MAX_GROWTH of the seeds' box a side."""
    seeds = np.asarray(seeds, bool)
    pool = np.flatnonzero((np.asarray(candidates, bool) & _near_box(points, seeds)) | seeds)
    spacing = median_spacing(points[seeds])
    if spacing <= 0 or len(pool) == seeds.sum():
        return seeds.copy()
    label = linked_groups(points[pool], LINK_SPACINGS * spacing)
    out = seeds.copy()
    out[pool[np.isin(label, np.unique(label[seeds[pool]]))]] = True
    return out


def mounted_points(points: np.ndarray, obj: np.ndarray, off_wall: np.ndarray, wall: Plane) -> np.ndarray:
    """(N,) bool: what the object hangs on (a plaque, a board): the points (N, 3) off the wall (``off_wall``), not the
    object's (``obj``) but within MAX_GROWTH of its box a side, no farther from the wall than its median point, and
    with no wall showing between them and the object (seen along the wall's normal, no wall point within
    MOUNT_GAP_SPACINGS of the wall points' spacing of the line to the object's middle); none when fewer than
    MOUNT_MIN_POINTS are. Its plain faces give SfM too few points to link (`linked_points`); a curtain, a door frame or
    a picture beside the object stand off the wall too, but wall shows between them and it."""
    from scipy.spatial import cKDTree

    obj = np.asarray(obj, bool)
    height = wall.height(points)
    mount = np.asarray(off_wall, bool) & ~obj & _near_box(points, obj) & (height <= np.median(height[obj]))
    on_wall = np.abs(np.nan_to_num(height, nan=np.inf)) <= wall.threshold
    feet = points - height[:, None] * wall.normal  # each point's foot on the wall
    gap = MOUNT_GAP_SPACINGS * median_spacing(feet[on_wall]) if on_wall.sum() >= 2 else 0.0
    if mount.sum() < MOUNT_MIN_POINTS or not gap > 0:  # too few for a surface, or no telling wall from a gap in it
        return np.zeros_like(mount)
    candidates = np.flatnonzero(mount)
    start = feet[candidates]
    end = np.median(feet[obj], axis=0)[None]  # the object's middle: a stray point of it is no way through
    length = np.linalg.norm(end - start, axis=1)
    # samples a gap apart (at most MOUNT_GAP_SAMPLES a line, then each reaches half their spacing), both ends included
    steps = np.clip(np.ceil(length / gap).astype(np.int64), 1, MOUNT_GAP_SAMPLES - 1) + 1
    reach = np.maximum(gap, 0.5 * length / (steps - 1))
    line = np.repeat(np.arange(len(candidates)), steps)
    t = (np.arange(len(line)) - np.repeat(np.cumsum(steps) - steps, steps)) / np.repeat(steps - 1, steps)
    along = start[line] + t[:, None] * (end - start)[line]
    inner = (t * length[line] >= gap) & ((1 - t) * length[line] >= gap)  # a wall point beside either end is no gap
    distance = cKDTree(feet[on_wall]).query(along, distance_upper_bound=float(reach.max()))[0]
    hit = (distance <= reach[line]) & inner
    blocked = np.bincount(line, weights=hit, minlength=len(candidates)) > 0
    mount[candidates[blocked]] = False
    return mount if mount.sum() >= MOUNT_MIN_POINTS else np.zeros_like(mount)


def _near_box(points: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """(N,) bool: the points within MAX_GROWTH of the seed points' box a side."""
    lo, hi = points[seeds].min(axis=0), points[seeds].max(axis=0)
    reach = MAX_GROWTH * (hi - lo)
    return np.all((points >= lo - reach) & (points <= hi + reach), axis=1)


def median_spacing(points: np.ndarray) -> float:
    """The median distance from each of the points (N, 3) to its nearest other one."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))


def linked_groups(points: np.ndarray, distance: float) -> np.ndarray:
    """(N,) the group label of each point when points closer than `distance` are linked and links chain."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(points).query_pairs(distance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    return connected_components(graph, directed=False)[1]
