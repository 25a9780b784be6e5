"""Put any capture into one canonical frame: upright (+Z up), centred, scaled to a box of about [-1, 1]^3.

One set of training defaults then works for a coin or a building. The similarity used is stored
(`world_from_source`) so meshes go back to the original frame exactly. Pure numpy on a `Scene`.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from recon.capture.region import linked_groups, median_spacing, object_region
from recon.capture.scene import Frame, Scene
from recon.config import NormalizeConfig
from recon.errors import InputError

OBJECT_MAX_MEAN_VIEW = 0.9
"""Cameras count as 'around the object' when the mean of their unit view directions is shorter than this."""
ARC_MAX_MEAN_VIEW = 0.96
"""... and, up to this, cameras on a narrower arc (an object's front only: on a shelf, against a wall; a 90° arc at
the usual heights gives 0.92) when they converge on a point and the object region found there stands on a support
with the background around it (`narrow_arc`): a facade or a forward-facing scene has no such object."""
BACKGROUND_FRACTION = 0.3
"""An object capture whose sparse points lie outside the object region more than this is an object on a
background (table, room): the field contracts and models the space around the box too."""
MIN_GROUP_FRACTION = 0.02
"""The box ignores groups of linked sparse points that hold fewer than this fraction of the points."""


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b (Rodrigues; handles a ≈ -b)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-9:  # opposite: rotate 180° about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        flip = 2 * np.outer(axis, axis) - np.eye(3)  # 180° about axis ⟂ a: a -> -a
        return rotation_between(-a, b) @ flip  # then the small remaining turn, exact up to rounding
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def estimate_up(c2ws: np.ndarray, mode: str) -> tuple[np.ndarray, str]:
    """The source-frame direction that should become +Z, and why.

    auto: mean of the cameras' up vectors (+Y of each camera), re-averaged over those within 45° of the
    first mean so a few rolled photos don't tilt the scene. Falls back to the normal of the plane of the
    camera centres when the up vectors cancel out (cameras rolled every which way).
    """
    if mode == "z":
        return np.array([0.0, 0.0, 1.0]), "source +Z kept as up (normalize.up=z)"
    if mode == "y":
        return np.array([0.0, 1.0, 0.0]), "source +Y taken as up (normalize.up=y)"
    ups = c2ws[:, :3, 1]
    mean = ups.mean(axis=0)
    rights = c2ws[:, :3, 0]
    evals, evecs = np.linalg.eigh(rights.T @ rights / len(rights))
    if len(rights) >= 3 and evals[0] < 0.02 and evals[1] > max(0.03, 5 * evals[0]) and np.linalg.norm(mean) > 0.3:
        # photos taken without roll: every camera's right vector is level, so up is orthogonal to all of them; from an
        # arc as narrow as 40° the right vectors still span the level plane (the mean up vector of photos looking
        # down tilts by their mean downward look)
        up = evecs[:, 0] * np.sign(evecs[:, 0] @ mean)
        return up, f"orthogonal to every camera's (level) right vector (residual tilt {np.degrees(np.sqrt(max(evals[0], 0.0))):.2f}°)"
    if np.linalg.norm(mean) > 0.3:
        inliers = ups[ups @ (mean / np.linalg.norm(mean)) > np.cos(np.radians(45))]
        if 2 * len(inliers) > len(ups):  # a majority must agree, else the mean of random rolls decides
            up = inliers.mean(axis=0)
            up /= np.linalg.norm(up)
            return up, f"mean camera up vector ({len(inliers)}/{len(ups)} cameras agree within 45°)"
    centers = c2ws[:, :3, 3]
    if len(centers) >= 3:
        _, sv, vt = np.linalg.svd(centers - centers.mean(axis=0))
        if sv[1] > 1e-6 * max(sv[0], 1e-30) and sv[2] < 0.5 * sv[1]:
            normal = vt[2]
            # sign: toward the cameras' mean up and against their mean view (photos look level or down); the
            # view alone decides for top-down shots, whose up vectors are horizontal
            if normal @ (mean + c2ws[:, :3, 2].mean(axis=0)) < 0:
                normal = -normal
            return normal, "camera up vectors disagree; up is the normal of the plane of the camera centres"
    raise InputError(
        "Cannot tell which way is up: the cameras' up vectors point in all directions and their centres do not "
        "lie on a plane. Set it explicitly with --set normalize.up=z (or y) to keep the source frame's axis."
    )


def facing_front(c2ws: np.ndarray, frames: list[Frame], R: np.ndarray) -> np.ndarray:
    """Rotation about +Z that makes the first photo (by name) look along +Y, like Blender's front view.

    Fixing the heading this way makes the normalized frame independent of the source frame's yaw.
    """
    first = min(range(len(frames)), key=lambda i: frames[i].name)
    view = R @ -c2ws[first, :3, 2]
    if np.hypot(view[0], view[1]) < 1e-6:  # looking straight down/up: use its up vector as the heading
        view = R @ c2ws[first, :3, 1]
    angle = np.arctan2(view[0], view[1])  # rotate the heading onto +Y
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def focus_point(c2ws: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares point nearest to every camera's optical axis, and the fraction of cameras it is in front of."""
    origins = c2ws[:, :3, 3]
    dirs = -c2ws[:, :3, 2]
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    A = proj.sum(axis=0)
    b = (proj @ origins[:, :, None]).sum(axis=0)[:, 0]
    if np.linalg.cond(A) > 1e8:  # all axes parallel (or a single camera): no unique focus
        return origins.mean(axis=0) + dirs.mean(axis=0), 0.0
    p = np.linalg.solve(A, b)
    in_front = float(np.mean(((p - origins) * dirs).sum(axis=1) > 0))
    return p, in_front


def view_spread(c2ws: np.ndarray) -> tuple[float, np.ndarray, float]:
    """The length of the mean of the cameras' unit view directions (1: all alike), their focus (`focus_point`) and the
    fraction of cameras it is in front of."""
    focus, in_front = focus_point(c2ws)
    return float(np.linalg.norm((-c2ws[:, :3, 2]).mean(axis=0))), focus, in_front


def classify_capture(c2ws: np.ndarray) -> tuple[str, np.ndarray, str]:
    """'object' (cameras around a point, looking at it) or 'unbounded' (forward-facing / looking out)."""
    mean_view, focus, in_front = view_spread(c2ws)
    if len(c2ws) >= 3 and in_front >= 0.9 and mean_view < OBJECT_MAX_MEAN_VIEW:
        return "object", focus, (
            f"object capture: the cameras look inward at a common point (in front of {in_front:.0%} of them) "
            f"from spread-out directions (mean view length {mean_view:.2f} < {OBJECT_MAX_MEAN_VIEW})"
        )
    return "unbounded", focus, (
        f"unbounded/forward capture: views are {'nearly parallel' if mean_view >= OBJECT_MAX_MEAN_VIEW else 'not converging'} "
        f"(mean view length {mean_view:.2f}, common point in front of {in_front:.0%} of the cameras)"
    )


def narrow_arc(c2ws: np.ndarray) -> float | None:
    """The mean view length of cameras that converge on a point in front of (nearly) all of them from an arc too
    narrow to count as around an object by itself (OBJECT_MAX_MEAN_VIEW up to ARC_MAX_MEAN_VIEW); None otherwise."""
    mean_view, _, in_front = view_spread(c2ws)
    return mean_view if len(c2ws) >= 3 and in_front >= 0.9 and OBJECT_MAX_MEAN_VIEW <= mean_view < ARC_MAX_MEAN_VIEW \
        else None


def similarity(scale: float, R: np.ndarray, center: np.ndarray) -> np.ndarray:
    """4×4 x ↦ scale · R · (x − center)."""
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = -scale * R @ center
    return T


def transform_c2w(T: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Apply a similarity to a camera pose, keeping the rotation orthonormal (scale moves the centre only)."""
    scale = np.cbrt(np.linalg.det(T[:3, :3]))
    R = T[:3, :3] / scale
    out = np.eye(4)
    out[:3, :3] = R @ c2w[:3, :3]
    out[:3, 3] = T[:3, :3] @ c2w[:3, 3] + T[:3, 3]
    return out


def _box_from_points(points: np.ndarray, link_spacings: float) -> np.ndarray | None:
    """The extent (2, 3) of the sparse points less stray ones, or None below 20 points.

    Points closer than `link_spacings` times the median nearest-neighbour distance are linked; the box
    holds the linked groups with at least `MIN_GROUP_FRACTION` of the points. A stray triangulation sits
    alone, while a thin part (a rod, a stem) is a chain of points a few spacings apart. Percentile trimming
    cut such parts: on the generator's thin scene the 2 %/98 % box, margin included, ended 0.17 below the
    rod's top (8 of 1,453 points lie above the cut, the last two 5 spacings beyond the others).
    """
    finite = points[np.all(np.isfinite(points), axis=1)]
    if len(finite) < 20:
        return None
    spacing = median_spacing(finite)
    if spacing > 0:
        label = linked_groups(finite, link_spacings * spacing)
        size = np.bincount(label)
        finite = finite[size[label] >= MIN_GROUP_FRACTION * len(finite)]
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    if np.any(hi - lo <= 0):
        return None
    return np.stack([lo, hi])


def _box_from_cameras(c2ws: np.ndarray, frames: list[Frame], focus: np.ndarray) -> np.ndarray:
    """Without sparse points: assume the object about fills the narrowest view at the median camera distance."""
    dist = float(np.median(np.linalg.norm(c2ws[:, :3, 3] - focus, axis=1)))
    half_fov = min(min(np.arctan(0.5 * f.w / f.fl_x), np.arctan(0.5 * f.h / f.fl_y)) for f in frames)
    half = max(dist * np.tan(half_fov), 1e-12)
    return np.stack([focus - half, focus + half])


def _distance_range(c2w: np.ndarray, points: np.ndarray, percentile: float) -> tuple[float, float] | None:
    """near/far (`recon.capture.scene.RAY_DISTANCE`) that the camera's rays travel to the points in front of it (percentiles)."""
    if len(points) < 10:
        return None
    offset = points - c2w[:3, 3]
    in_front = offset @ (-c2w[:3, 2]) > 0
    dist = np.linalg.norm(offset[in_front], axis=1)
    if len(dist) < 10:
        return None
    return float(np.percentile(dist, percentile)), float(np.percentile(dist, 100 - percentile))


def box_corners(box: np.ndarray) -> np.ndarray:
    """The 8 corners (8, 3) of an axis-aligned box (2, 3)."""
    return np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _box_distance_range(c2w: np.ndarray, aabb: np.ndarray) -> tuple[float, float]:
    """near/far (`recon.capture.scene.RAY_DISTANCE`) bounding every ray's segment inside the box: the distance from the camera
    centre to the box (0 inside it) and to its farthest corner (a box's farthest point is a corner)."""
    origin = c2w[:3, 3]
    corners = box_corners(aabb)
    near = float(np.linalg.norm(origin - np.clip(origin, aabb[0], aabb[1])))
    return near, float(np.linalg.norm(corners - origin, axis=1).max())


FEW_PHOTOS = 20
"""Up to this many photos every photo trains the field: a casual capture cannot spare views, and the mesh needs
them all. Its PSNR is then measured on training photos (said in the reasons), never called held-out. Above it, no
more photos are held out than leave this many to train: one more photo never trains the field on fewer."""


def assign_split(frames: list[Frame], test_every: int, val_every: int) -> str:
    """Keep a split the source gave; otherwise hold out every Nth photo by name (deterministic), as many as leave
    FEW_PHOTOS to train (then spread evenly by name)."""
    if any(f.split for f in frames):
        for f in frames:
            f.split = f.split or "train"
        return "split given by the source"
    order = sorted(range(len(frames)), key=lambda i: frames[i].name)
    if len(frames) <= FEW_PHOTOS:
        for f in frames:
            f.split = "train"
        return (f"only {len(frames)} photos (<= {FEW_PHOTOS}): all train the field that makes the mesh; PSNR is measured "
                f"on training photos, not held-out ones")
    wanted = {rank: "test" for rank in range(0, len(frames), test_every)} if test_every else {}
    if val_every:
        wanted.update({rank: "val" for rank in range(val_every // 2, len(frames), val_every) if rank not in wanted})
    spare = len(frames) - FEW_PHOTOS
    capped = len(wanted) > spare
    if capped:  # as many as leave FEW_PHOTOS to train, tests first, spread evenly by name
        kinds = sorted(wanted.values(), key=lambda kind: kind != "test")[:spare]
        wanted = dict(zip(np.linspace(0, len(frames), len(kinds), endpoint=False).round().astype(int).tolist(), kinds))
    for rank, i in enumerate(order):
        frames[i].split = wanted.get(rank, "train")
    counts = {s: sum(f.split == s for f in frames) for s in ("train", "val", "test")}
    held = [f"every {test_every}th photo held out for test"] if test_every else []
    held += [f"every {val_every}th (offset) for validation" if test_every else
             f"every {val_every}th photo (offset) held out for validation"] if val_every else []
    if not held:
        return f"no photo held out (normalize.test_every=0): PSNR is measured on training photos: {counts}"
    if not val_every:
        held[-1] += " (they also show the training's progress; normalize.val_every holds out others for that)"
    if capped:
        held.append(f"at most {spare} so that {FEW_PHOTOS} train")
    return f"{', '.join(held)}: {counts}"


def _drop_nonfinite_points(scene: Scene) -> Scene:
    """The scene without sparse points that have NaN/inf coordinates (visibility indices renumbered)."""
    points = np.asarray(scene.points, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(points), axis=1)
    if keep.all():
        return scene
    new_index = np.cumsum(keep) - 1
    colors = np.asarray(scene.point_colors).reshape(-1, 3)
    visibility = {
        name: new_index[idx[keep[idx]]] for name, idx in ((n, np.asarray(v, dtype=np.int64)) for n, v in scene.point_visibility.items())
    }
    errors = scene.point_errors
    return replace(
        scene, points=points[keep], point_colors=colors[keep] if len(colors) == len(points) else colors,
        point_visibility=visibility, point_errors=errors[keep] if errors is not None and len(errors) == len(points) else None,
    )


def normalize(scene: Scene, cfg: NormalizeConfig, holds: np.ndarray | None = None) -> Scene:
    """The canonical scene: +Z up, centred on the object (or the points), scaled so the box fits [-1, 1]^3.

    holds: points (N, 3) in `scene`'s frame that an object capture's box must hold besides its sparse points (the
    masks' visual hull: `recon.stages.normalize`)."""
    if len(scene.frames) < 1:
        raise InputError("The scene has no cameras to normalize.")
    c2ws = np.stack([f.c2w for f in scene.frames])
    if not np.all(np.isfinite(c2ws)):
        raise InputError("Some camera poses contain NaN or infinite values; re-run the poses stage.")
    spread = float(np.linalg.norm(c2ws[:, :3, 3] - c2ws[:, :3, 3].mean(axis=0), axis=1).max())
    if spread <= 1e-12 * float(np.abs(c2ws[:, :3, 3]).max()):  # relative: scale-free, and 0 <= 0 for one camera
        raise InputError(
            f"All {len(scene.frames)} camera(s) sit at the same point (a single photo or a rotation-only/panorama "
            "capture): without moving the camera between photos there is no parallax, so depth cannot be "
            "recovered. Take the photos while walking around the object."
        )
    scene = _drop_nonfinite_points(scene)
    notes: dict[str, str] = {}
    up, notes["up"] = estimate_up(c2ws, cfg.up) if cfg.up != "none" else (np.array([0.0, 0, 1]), "rotation kept")
    R = rotation_between(up, np.array([0.0, 0.0, 1.0]))
    R = facing_front(c2ws, scene.frames, R) @ R
    capture, focus, notes["capture"] = classify_capture(c2ws)

    points = np.asarray(scene.points, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    centers = c2ws[:, :3, 3]
    region = ground = region_points = aside_points = None
    arc = narrow_arc(c2ws) if capture != "object" else None
    if capture == "object" or arc is not None:
        center = focus
        found = object_region(
            points, c2ws, np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in scene.frames]),
            np.array([[f.w, f.h] for f in scene.frames]), focus, up, leave_aside=cfg.beside == "auto",
        )
    if arc is not None:
        if found is not None and found.ground is not None and found.background_fraction > BACKGROUND_FRACTION:
            capture = "object"
            support = "stands on the ground" if found.ground.kind == "ground" else "hangs on a wall"
            notes["capture"] = (
                f"object capture from one side: the cameras converge on a point in front of them from an arc (mean "
                f"view length {arc:.2f}, under {ARC_MAX_MEAN_VIEW}), and what they converge on {support} with "
                f"{found.background_fraction:.0%} of the points around it: an object's front photographed"
            )
        else:
            notes["capture"] = (
                f"unbounded capture: the cameras converge on a point from an arc (mean view length {arc:.2f}), but "
                f"what they converge on is no object standing on a support with background around it (a facade, a "
                f"scene): modelled whole"
            )
    if capture == "object":
        if found is not None:
            # the object the cameras look at (and, below it, down to the ground it stands on)
            box = _box_from_points((points[found.points & ~found.mount] - center) @ R.T, cfg.link_spacings)
            if box is not None and found.mount.any():  # what the object hangs on: too few points to pass as a group
                mount = (points[found.mount] - center) @ R.T
                box = np.stack([np.minimum(box[0], mount.min(axis=0)), np.maximum(box[1], mount.max(axis=0))])
            notes["region"] = found.reason
            if box is not None and found.ground is not None:
                n = R @ found.ground.normal
                ground = np.array([*n, found.ground.offset - found.ground.normal @ center])  # centred, rotated frame
                if found.ground.kind == "ground":
                    foot = (ground[3] - n[:2] @ box.mean(axis=0)[:2]) / n[2]  # ground height under the box centre
                    box[0, 2] = min(box[0, 2], foot)
            if box is not None and found.background_fraction > BACKGROUND_FRACTION and not scene.has_alpha:
                capture = "unbounded"
                notes["capture"] += (
                    f"; {found.background_fraction:.0%} of the sparse points are background (table, room): the box holds "
                    f"the object and the space around it is contracted and modelled too"
                )
            region = box
            region_points, aside_points = found.points, found.aside
        else:
            # points of the object: those nearer to the focus than the cameras are (drops walls/background)
            radius = np.median(np.linalg.norm(centers - focus, axis=1))
            near_obj = finite & (np.linalg.norm(points - focus, axis=1) < radius)
            box = _box_from_points((points[near_obj] - center) @ R.T, cfg.link_spacings)
        notes["box"] = ("the object region's sparse points (stray points dropped)" if region is not None else
                        "sparse points around the focus (stray points dropped)") if box is not None else ""
        if holds is not None and box is not None:
            held = (np.asarray(holds, np.float64).reshape(-1, 3) - center) @ R.T
            held_lo, held_hi = held.min(axis=0), held.max(axis=0)
            grown = np.stack([np.minimum(box[0], held_lo), np.maximum(box[1], held_hi)])
            growth = float(((grown[1] - grown[0]) / (box[1] - box[0])).max())
            if growth > 1.01:
                box = grown
                if region is not None:  # the object is what the masks show: the mesh region holds it too
                    region = np.stack([np.minimum(region[0], held_lo), np.maximum(region[1], held_hi)])
                notes["box"] += (f", grown to hold the masks' visual hull (up to {growth - 1:.0%} longer a side): "
                                 f"the masks show parts of the object that have no sparse points")
    else:
        center = np.median(points[finite], axis=0) if finite.sum() >= 20 else focus
        box = _box_from_points((points[finite] - center) @ R.T, cfg.link_spacings)
        notes["box"] = "sparse points (stray points dropped)" if box is not None else ""
    if box is None:
        box = _box_from_cameras(c2ws, scene.frames, focus) - focus
        notes["box"] = "no sparse points: box from the cameras' field of view at their distance"
    if capture != "object" and region is None:
        # keep the cameras inside the modelled region of a forward/unbounded capture
        cam_box = np.stack([((centers - center) @ R.T).min(0), ((centers - center) @ R.T).max(0)])
        box = np.stack([np.minimum(box[0], cam_box[0]), np.maximum(box[1], cam_box[1])])
    size = box[1] - box[0]
    box = box + np.stack([-size, size]) * cfg.box_margin
    extent = float(np.abs(box).max())
    if not np.isfinite(extent) or extent <= 0:
        raise InputError("The scene has no extent (all cameras and points coincide); the capture cannot be scaled.")
    scale = 1.0 / extent
    T = similarity(scale, R, center)
    aabb = box * scale

    if region is not None:
        region = region * scale
    if ground is not None:
        ground = np.array([*ground[:3], ground[3] * scale])
    new_frames = [replace(f, c2w=transform_c2w(T, f.c2w)) for f in scene.frames]
    new_points = (points - center) @ R.T * scale
    for f, old in zip(new_frames, scene.frames, strict=True):
        near, far = _box_distance_range(f.c2w, aabb)
        if capture != "object":
            visible = scene.point_visibility.get(old.name)
            pts = new_points[visible] if visible is not None and len(visible) else new_points[finite]
            rng = _distance_range(f.c2w, pts, cfg.depth_percentile)
            if rng is not None:
                near, far = rng[0] * 0.8, max(rng[1] * 1.2, far)
        f.near = float(max(near, 1e-3 * float(np.linalg.norm(f.c2w[:3, 3]) + 1e-3), 1e-4))
        f.far = float(max(far, f.near * 1.01))
    notes["split"] = assign_split(new_frames, cfg.test_every, cfg.val_every)
    notes["scale"] = f"scale {scale:.6g}: the box's largest half-extent becomes 1"
    return Scene(
        frames=new_frames,
        points=new_points,
        point_colors=scene.point_colors,
        point_visibility=scene.point_visibility,
        point_errors=scene.point_errors,
        aabb=aabb,
        region=region,
        region_points=region_points,
        aside_points=aside_points,
        ground=ground,
        capture=capture,
        world_from_source=T @ scene.world_from_source,
        has_alpha=scene.has_alpha,
        source_kind=scene.source_kind,
        notes=notes,
        root=scene.root,
        source=scene.source,
    )
