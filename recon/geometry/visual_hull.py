"""The visual hull: the space no photo sees as background, as a signed distance on a grid.

Why: a surface field starts from a closed shape and keeps it where no photo says otherwise (an underside no camera
sees). The SfM points' convex hull is such a shape, but its faces pass wherever the points happen to end: few
points lie on a base's bottom edges, so on the generator's thin scene the hull's bottom runs 0.01-0.06 units above
the true bottom, and the mesh followed it. Silhouettes (masks, or a keyed backdrop) bound the object from every
photo at once: carve every grid vertex that projects onto background, and what is left contains the object, down
to the lowest edges the photos see.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from recon.camera import project

__all__ = ["carve", "free_space", "hull_bounds", "hull_silhouettes", "silhouette", "visual_hull_sdf"]

SIGHTING_CHUNK = 1 << 16
"""Grid points `_sightings` projects into every photo at a time: a 96³ grid's arrays whole outrun the cache, a
chunk's stay in it (the counts are the same)."""
SPLAT_OCTAVE = 1.0
"""`silhouette` splats together the hull vertices whose spacing in the photo is within 2**SPLAT_OCTAVE of each other."""
SPLAT_PX = 8.0
"""A splat is closed on a grid with at most this many pixels between neighbouring vertices; coarser ones are drawn
on a coarser grid and read back at the photo's pixels."""


def carve(box: np.ndarray, res: int, c2ws: Sequence[np.ndarray], intrinsics: Sequence[Sequence[float]],
          objects: Sequence[np.ndarray], min_views: int = 1, margin_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(inside (res, res, res) bool, carved_by (res, res, res) int): the vertices of a res³ grid over box (2, 3),
    indexed [ix, iy, iz], that fewer than `min_views` photos see as background, and how many do.

    objects[k]: photo k's (H, W) bool object pixels. A vertex is seen as background by a photo when it lies in
    front of the camera, inside the frame, and more than `margin_px` pixels from the photo's object pixels.
    Vertices outside a photo's frame learn nothing from it. The defaults carve what any one photo calls background:
    near a surface only the photos that see it edge-on carve, so asking for two (or a margin) leaves a shell two to
    three times as far from the true surface.
    """
    carved_by, _ = _sightings(_grid(box, res), c2ws, intrinsics, objects, margin_px)
    carved_by = carved_by.reshape(res, res, res)
    return carved_by < min_views, carved_by


FREE_SPACE_VOTES = 2
"""`free_space` frees a grid vertex that at least this many sightlines pass: one false match's sightlines, each
alone, free nothing."""
FREE_SPACE_STOP_CELLS = 1.5
"""A sightline stops this many grid cells short of its point: the surface it lies on, and its triangulation's
error, keep their vertices."""


def free_space(box: np.ndarray, res: int, sightlines: Sequence[tuple[np.ndarray, np.ndarray]],
               min_votes: int = FREE_SPACE_VOTES, stop_cells: float = FREE_SPACE_STOP_CELLS) -> np.ndarray:
    """(res, res, res) bool: the vertices of a res³ grid over box (2, 3), indexed [ix, iy, iz], that at least
    `min_votes` sightlines pass within half a cell of: a camera saw a sparse point through them, so they are empty.

    Why: silhouettes carve no concavity (a bowl's hollow, the wedge under an overhang): the visual hull fills it to
    the rim, and a field started there keeps a lid. The SfM points on the hollow's inner surface were seen from the
    cameras above it, through the lid. sightlines: per photo, (its camera centre (3,), the points (N, 3) it
    observes); each runs from the camera to `stop_cells` short of the point, within the box."""
    box = np.asarray(box, np.float64)
    lo, hi = box
    cell = (hi - lo) / (res - 1)
    step = 0.5 * float(cell.min())
    votes = np.zeros(res ** 3, np.int64)
    for eye, points in sightlines:
        eye, points = np.asarray(eye, np.float64), np.asarray(points, np.float64).reshape(-1, 3)
        if not len(points):
            continue
        offset = points - eye
        length = np.linalg.norm(offset, axis=1)
        ok = length > 0
        direction = offset[ok] / length[ok, None]
        length = length[ok] - stop_cells * float(cell.max())
        with np.errstate(divide="ignore", invalid="ignore"):  # rays along an axis: ±inf, as the slab test wants
            t0, t1 = (lo - eye) / direction, (hi - eye) / direction
        enter = np.nanmax(np.minimum(t0, t1), axis=1).clip(min=0.0)
        leave = np.minimum(np.nanmin(np.maximum(t0, t1), axis=1), length)
        count = np.where(leave > enter, np.ceil((leave - enter) / step).astype(np.int64) + 1, 0)
        if not count.sum():
            continue
        line = np.repeat(np.arange(len(count)), count)
        k = np.arange(len(line)) - np.repeat(np.cumsum(count) - count, count)
        t = np.minimum(enter[line] + k * step, leave[line])
        vertex = np.rint((eye + t[:, None] * direction[line] - lo) / cell).astype(np.int64)
        inside = np.all((vertex >= 0) & (vertex < res), axis=1)
        flat = (vertex[inside, 0] * res + vertex[inside, 1]) * res + vertex[inside, 2]
        passed = np.unique(line[inside] * res ** 3 + flat)  # each sightline votes once a vertex
        votes += np.bincount(passed % res ** 3, minlength=res ** 3)
    return (votes >= min_votes).reshape(res, res, res)


def hull_bounds(box: np.ndarray, res: int, c2ws: Sequence[np.ndarray], intrinsics: Sequence[Sequence[float]],
                objects: Sequence[np.ndarray], min_seen: float = 0.25,
                support: np.ndarray | None = None) -> np.ndarray | None:
    """(2, 3) bounds of the vertices of a res³ grid over box that at most one photo sees as background and at least
    `min_seen` of the photos see in their frame, or None when no vertex is such.

    Why: a box fitted to an object's sparse points misses its plain parts (no texture, no points), which its masks
    still show; the field cannot model what lies outside its box. One photo's wrong mask carves nothing here, and
    space few photos see (beyond the frames' edges, where nothing carves) does not count as object.
    support: the plane (4,) (n, d) the object stands or hangs on, n towards the object: vertices more than a cell
    behind it do not count either (every photo sees the space under a table's object in front of the object)."""
    pts = _grid(box, res)
    carved_by, seen_by = _sightings(pts, c2ws, intrinsics, objects)
    kept = (carved_by <= 1) & (seen_by >= max(1, int(np.ceil(min_seen * len(objects)))))
    if support is not None:
        cell = float(np.max(np.asarray(box, np.float64)[1] - np.asarray(box, np.float64)[0])) / (res - 1)
        kept &= pts @ np.asarray(support[:3], np.float64) >= float(support[3]) - cell
    if not kept.any():
        return None
    return np.stack([pts[kept].min(axis=0), pts[kept].max(axis=0)])


def _grid(box: np.ndarray, res: int) -> np.ndarray:
    """The vertices (res³, 3) of a res³ grid over box (2, 3), in [ix, iy, iz] order."""
    box = np.asarray(box, np.float64)
    axes = [np.linspace(box[0, i], box[1, i], res) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _sightings(pts: np.ndarray, c2ws: Sequence[np.ndarray], intrinsics: Sequence[Sequence[float]],
               objects: Sequence[np.ndarray], margin_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(how many photos see each point as background, how many see it at all): in front of the camera and inside
    the frame, background when more than `margin_px` pixels from the photo's object pixels."""
    import cv2

    carved_by = np.zeros(len(pts), np.int32)
    seen_by = np.zeros(len(pts), np.int32)
    kernel = np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8) if margin_px > 0 else None
    photos = []
    for c2w, intr, obj in zip(c2ws, intrinsics, objects, strict=True):
        obj = np.asarray(obj, np.uint8)
        photos.append((np.asarray(c2w, np.float64), np.asarray(intr, np.float64),
                       obj if kernel is None else cv2.dilate(obj, kernel)))
    for s in range(0, len(pts), SIGHTING_CHUNK):  # every photo for a chunk of points: its arrays stay in the cache
        chunk, carved, seen_in = pts[s : s + SIGHTING_CHUNK], carved_by[s : s + SIGHTING_CHUNK], seen_by[s : s + SIGHTING_CHUNK]
        for c2w, intr, obj in photos:
            h, w = obj.shape
            uv, z = project(chunk, c2w, intr)
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            seen = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            seen_in += seen
            carved[seen] += obj[row[seen], col[seen]] == 0
    return carved_by, seen_by


def visual_hull_sdf(inside: np.ndarray, box: np.ndarray, smooth_cells: float = 1.0) -> np.ndarray:
    """Signed distance (res, res, res) float32 (negative inside, world units) of the vertices `inside` (a res³ grid
    over box (2, 3)); the box's outer layer counts as outside, so the shape closes inside its box.

    From two Euclidean distance transforms, the boundary put half a cell between inside and outside vertices, then
    Gaussian-smoothed over `smooth_cells` cells: the carved grid's staircase would otherwise be the start's surface."""
    from scipy import ndimage

    box = np.asarray(box, np.float64)
    res = inside.shape[0]
    cell = (box[1] - box[0]) / (res - 1)
    solid = inside.copy()
    solid[[0, -1], :, :] = solid[:, [0, -1], :] = solid[:, :, [0, -1]] = False
    if not solid.any():
        raise ValueError("nothing is left inside the visual hull")
    outside_d = ndimage.distance_transform_edt(~solid, sampling=cell)
    inside_d = ndimage.distance_transform_edt(solid, sampling=cell)
    half = 0.5 * float(cell.min())
    sdf = np.where(solid, half - inside_d, outside_d - half)
    if smooth_cells > 0:
        sdf = ndimage.gaussian_filter(sdf, smooth_cells)
    return sdf.astype(np.float32)


def hull_silhouettes(box: np.ndarray, res: int, c2ws: Sequence[np.ndarray], intrinsics: Sequence[Sequence[float]],
                     objects: Sequence[np.ndarray], tolerance: float,
                     voters: Sequence[bool] | None = None) -> tuple[list[np.ndarray], np.ndarray]:
    """(per photo, the (H, W) bool pixels the photos' common hull covers; carved_by as `carve` returns it).

    The hull keeps every vertex of a res³ grid over box that at most `tolerance` of the voting photos (at least one)
    see as background, so one photo's wrong object pixels carve nothing the others show; each photo's silhouette is
    the hull's outer vertices splatted into it (`silhouette`), the size of its `objects` mask. voters (per photo,
    default all): the photos whose masks carve; every photo gets its silhouette."""
    from scipy.ndimage import binary_erosion

    box = np.asarray(box, np.float64)
    carving = [k for k in range(len(objects)) if voters is None or voters[k]]
    _, carved_by = carve(box, res, [c2ws[k] for k in carving], [intrinsics[k] for k in carving],
                         [objects[k] for k in carving])
    inside = carved_by <= max(1, int(tolerance * len(carving)))
    shell = inside & ~binary_erosion(inside)  # the hull's outer vertices project onto its whole silhouette
    hull_pts = _grid(box, res)[shell.reshape(-1)]
    cell = float(np.max(box[1] - box[0]) / (res - 1))
    silhouettes = [silhouette(hull_pts, cell, np.asarray(c2w, np.float64), np.asarray(intr, np.float64), *obj.shape[::-1])
                   for c2w, intr, obj in zip(c2ws, intrinsics, objects, strict=True)]
    return silhouettes, carved_by


def silhouette(hull_pts: np.ndarray, cell: float, c2w: np.ndarray, intr: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h, w) bool: the pixels the hull's vertices cover, each splatted as wide as a grid cell at its own depth.

    Vertices whose spacing in the photo lies within a factor two (`SPLAT_OCTAVE`) share one splat: a close-up sees the
    near side of the hull several times as coarsely as its far side, and one spacing for all left the near side's gaps
    open as holes in the silhouette."""
    import cv2

    out = np.zeros((h, w), bool)
    if not len(hull_pts):
        return out
    uv, z = project(hull_pts, c2w, intr)
    front = z > 1e-9
    uv, z = uv[front], z[front]
    spacing = cell * max(intr[0], intr[1]) / z  # pixels between neighbouring vertices at each one's depth
    octave = np.floor(np.log2(np.maximum(spacing, 1.0)) / SPLAT_OCTAVE).astype(np.int64)
    for level in np.unique(octave):
        pick = octave == level
        out |= _splat(cv2, uv[pick], float(spacing[pick].max()), float(spacing[pick].min()), w, h)
    return out


def _splat(cv2, uv: np.ndarray, spacing: float, least: float, w: int, h: int) -> np.ndarray:
    """(h, w) bool: points at most `spacing` pixels apart with the gaps between them closed and grown by half the
    `least` spacing, on a grid no finer than SPLAT_PX pixels a spacing (coarse splats cost what fine ones do),
    reaching in from points just beyond the frame."""
    scale = min(1.0, SPLAT_PX / spacing)
    gap = int(np.ceil(spacing * scale))  # close the gaps between splatted vertices, then grow by half a cell
    half = round(0.5 * least * scale)
    pad = gap + half + 1
    cw, ch = int(np.ceil(w * scale)), int(np.ceil(h * scale))
    px = np.floor(uv * scale).astype(np.int64) + pad
    keep = (px[:, 0] >= 0) & (px[:, 0] < cw + 2 * pad) & (px[:, 1] >= 0) & (px[:, 1] < ch + 2 * pad)
    if not keep.any():
        return np.zeros((h, w), bool)
    canvas = np.zeros((ch + 2 * pad, cw + 2 * pad), np.uint8)
    canvas[px[keep, 1], px[keep, 0]] = 1
    closing = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1))
    canvas = cv2.morphologyEx(canvas, cv2.MORPH_CLOSE, closing)
    if half > 0:
        canvas = cv2.dilate(canvas, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * half + 1, 2 * half + 1)))
    rows = pad + np.floor((np.arange(h) + 0.5) * scale).astype(np.int64)
    cols = pad + np.floor((np.arange(w) + 0.5) * scale).astype(np.int64)
    return canvas[rows][:, cols].astype(bool)
