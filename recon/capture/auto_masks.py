"""Object masks for captures that come without them: the object the cameras look at, cut out of every photo.

No learned weights. The sparse points of the object region (`recon.capture.region`) that SfM placed surely seed the
object, each its own pixel; the points on the cut support plane, the points outside the region and every pixel outside
the region's projected box seed the background; GrabCut (colour models and a graph cut, OpenCV) segments between them,
starting from the hull of the object seeds and their feet on the ground as probable object (an object stands on its
table: a plain, shadowed base has no seeds of its own).
Then the photos vote: a pixel stays object only where its ray passes through space that (almost) no photo calls
background — the masks' visual hull. How well each photo's cut agrees with the hull the others carve says how sure the
segmentation is. A close-up that crops the object has no background around it to learn from: when enough photos frame
the object, only they carve, and each close-up is cut again with the hull's silhouette as its probable object (one the
silhouette fills, showing no background point, takes the silhouette itself); so is a photo that frames the object but
whose cut left out much of what the others show (a plain board it hangs on).
On a table, the plane settles what colour cannot: pixels whose texture lines up with the other photos' views of the
table through its homography are table (a cast shadow the cut took), and the hull's pixels beside a cut whose rays go
on to meet the table where no other photo sees it bare are object (a shadowed base the cut left out).
Finally each cut's outline is snapped to its photo's edges and made as soft as they are (`matte`, a
guided filter).
Pure numpy/OpenCV on a normalized `Scene` and its photos; the caller decides what to do with unsure masks.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from recon.camera import (MIN_KEYPOINT_ERROR_PX, MIN_TRIANGULATION_DEG, intrinsic_matrix, pixel_centres, pixel_rays,
                          project, triangulation_angles)
from recon.capture.images import read_image, undistort
from recon.capture.normalization import box_corners
from recon.capture.region import support_kind
from recon.capture.scene import Frame, Scene
from recon.geometry.visual_hull import hull_silhouettes

SEGMENT_SIDE = 640
"""Photos are segmented at this longest side (pixels); the masks are written back at the photos' own size."""
REGION_MARGIN = 0.1
"""Outside the object region's box grown by this fraction of its size on each side, every pixel is background."""
BOX_EVERY_OBJECT_POINT = True
"""The cut's box holds every sparse point normalize took for the object. The scene's region box leaves out small
groups of them as stray triangulations, but a thin part reaching out of the object (a rod's top, an antenna) gives SfM
just as few points apart from the rest; the cuts and the hull they vote on then say whether it is object."""
GROUND_BAND = 0.02
"""Sparse points within this fraction of the region's size of the support plane are the plane's (background)."""
SEED_RADIUS = 0.004
"""Background seed discs around projected sparse points, as a fraction of the photo's diagonal. An object point seeds
only its own pixel: where object points are dense (a video's many frames) discs about the ones near the outline would
paint a band of table as sure object."""
SEED_SPREAD_PX = 1.5
"""An object point seeds the cut only when its triangulation places it within this many pixels of the segmented
photo: its reprojection error (at least `MIN_KEYPOINT_ERROR_PX`) over the sine of the widest angle between the rays
that observe it (at least `MIN_TRIANGULATION_DEG`), in the photo's pixels scaled to the segmented size. A video's short
baselines leave such uncertain points at the object's foot and silhouette, and each lands wherever its error puts it."""
STANDS_ON_SUPPORT = True
"""The cut starts with the hull of the object seeds and their feet on the ground as probable object: an object stands
on its table, and a plain or shadowed base holds no seeds of its own."""
MIN_PIECE = 0.02
"""Pieces of a cut smaller than this fraction of its largest seeded piece are dropped (a stray point's seed)."""
MAX_SPECK = 2e-4
"""Enclosed background pieces smaller than this fraction of the photo are noise in the cut and become object."""
HULL_RES = 96
"""Grid vertices per side of the visual hull the photos vote on."""
HULL_TOLERANCE = 0.1
"""A hull vertex survives while at most this fraction of the photos (at least one) call it background: one bad
cut must not carve the object out of every other photo. A larger share keeps more of a base the cuts bite but lies
fatter round every outline (benchmarks/results/auto_mask_hull_tolerance_*.json)."""
FRAMED_SHARE = 0.8
"""A photo frames the object when at least this share of the grown region box's outline lies in the photo: its cut
has background all round the object to learn the background's colours from. A close-up that crops the object has
little, and its cut takes what it cannot tell from the background (a plain board the object is mounted on) for
background, as the generated wall-mounted capture's close-ups do (`benchmarks/auto_mask_seeds.py`, variant
'close-ups vote', against 'shipped')."""
MIN_FRAMING_VOTERS = 6
"""When some photos do not frame the object and at least this many do, only the framing photos carve the hull (a
close-up's cut would carve what it took for background out of every photo's mask), and each close-up is cut again
with the hull's silhouette as its probable object and everything outside it as background."""
MIN_HULL_BACKGROUND = 0.01
"""... unless the silhouette leaves less than this share of the close-up outside it: then there is no background to
learn from there either: its first cut stays when it had MIN_BACKGROUND_SEEDS of its own (the wall seen through a gap
no framing photo sees through, which the hull fills), else the close-up's mask is the silhouette, the object as the
photos that frame it carved it (a cut without background seeds learns its background colours from the object's)."""
MIN_BACKGROUND_SEEDS = 3
"""See MIN_HULL_BACKGROUND: the background points a close-up's first cut needs to be trusted over the hull."""
MAX_HULL_MISSED = 0.35
"""A photo that frames the object is cut again the same way when its cut leaves out more than this share of the hull's
silhouette in it, which the other photos all show as object: a plain board the object hangs on has almost no sparse
points to seed it, so one photo's cut can give it all to the background
(benchmarks/results/auto_mask_short_cuts_wall_mounted.json). Well above what a good cut leaves out, so on the other
captures no photo is cut again (benchmarks/results/auto_mask_short_cuts_*.json)."""
HOLE_IN_HULL = 0.95
"""A hole a cut leaves inside the object is filled when at least this share of it lies in the hull's silhouette."""
FILL_GROUNDED_BITES = True
"""A cut's bite out of the object's base is given back: the silhouette pixels beside the cut whose rays meet the table
where (almost) no other photo sees table (see `_fill_grounded_bites`)."""
MIN_GROUND_VIEWS = 0.25
"""... a ray's table point counts only when at least this share of the other photos frame it."""
TABLE_PARTNERS = 4
"""Each photo is matched on the support plane with this many others (`_table_agreement`) ..."""
TABLE_WINDOW = 0.015
"""... in windows this fraction of the segmented photo's longer side across (9 px at 640)."""
MIN_TABLE_HALF_WINDOW = 3
"""... and at least this many pixels either side of the centre: a smaller window correlates by chance."""
TABLE_TEXTURE = 2.0
"""... where both photos' grey levels (0-255) vary by at least this standard deviation in the window."""
TABLE_NCC = 0.5
"""A pixel shows the table when its window correlates at least this well with two partners' views of the same patch of
the plane: shadowed table (a cast shadow is where it is from every side) as much as lit."""
TABLE_PARALLAX = 12.0
"""The partners are the photos that see the object's points moved off the plane's homography (their median) nearest
this many windows: the object's foot lines up with the table as far up as its parallax stays under half a window, so
the more parallax, the thinner the band of the foot the table step takes ..."""
MIN_TABLE_PARALLAX = 2.0
"""... and at least this many: from a nearby camera (a video's next frames) the whole object lines up through the
table's homography as well as the table does, and its texture would be taken for table ..."""
MAX_TABLE_TURN = 90.0
"""... among the photos that see the object from within this many degrees of this one: from farther round, the object
hides the table beside it that this photo sees."""
PARALLAX_POINTS = 500
"""The parallax is measured on at most this many of the object's points."""
DROP_TABLE = True
"""Cut pixels that show the table are dropped from the masks (`_drop_table`)."""
MIN_AGREEMENT = 0.9
"""The masks are trusted when, in the median photo, at least this fraction of the cut lies inside the hull all photos
carve (the hull is fatter than the object where no photo looks edge-on, so only the cut's excess counts)."""
MIN_SEED_RECALL = 0.9
"""... and the masks keep at least this fraction of the object's sparse points where the photos see them."""
REFUTED_KEPT = 0.25
"""An object point that at most this share of the photos' masks keep (among the photos it lands in) is refuted: the
masks, each cut from its own photo's colours, agree it is not object (a false match near the object, a table point
just above the plane's band). Refuted points do not count in the share of points the masks keep, ..."""
MAX_REFUTED = 0.1
"""... up to this share of the counted points, the most refuted first: a plain object has a few dozen points, so a
couple of false ones can hold good masks under MIN_SEED_RECALL (benchmarks/results/auto_mask_refuted_painted2.json),
while more than a tenth would be a part of the object every cut missed, which must still count."""
LONE_POINT_SPACING = 5.0
"""An object point farther than this many times the object points' median spacing from every other one is a false
match in the air and does not count in that fraction: every mask leaves it out, and a plain object has so few points
that three such points weigh a tenth."""
EDGE_PERCENTILE = 80
"""A pixel is an edge when its colour gradient is in the photo's top (100 - this) percent."""
ASTRAY_SHARE = 0.1
"""A photo whose mask comes out empty and that observes fewer than this share of the median photo's count of the
object's sparse points shows none of the object where SfM placed it (a photo misregistered on a few matches, or one
that misses the object): it is left out of the masked training rather than making every mask unsure. A photo that
sees the object's points and still gets an empty mask is a cut that failed, and does make them unsure."""
MAX_ASTRAY_SHARE = 0.1
"""... at most this share of the photos (at least one): more empty masks say the cuts failed, not a pose."""
MIN_EDGE_SUPPORT = 0.5
"""... and the median photo's mask outline runs along edges for at least this fraction of its length: seeds alone
(photos that do not show what their cameras should) give outlines that agree across photos but ignore the image."""
MATTE_RADIUS = 0.0075
"""`matte`'s guided filter reaches this fraction of the photo's longer side (12 px at 1600) across the outline."""
MATTE_EPS = 1e-2
"""... its edge threshold (variance of the photo's colour, in [0, 1] units): weaker edges than this are smoothed over."""
MATTE_CONTRAST = 2.0
"""... and its output is steepened this many times about 0.5, so the filter's faint spill onto the background is
cut and the outline stays about as soft as the photo's own edges. The three were chosen on the realistic generated
tabletop against its true masks blurred by each photo's own camera blur (`benchmarks/auto_mask_matte.py`)."""


@dataclass
class ObjectMasks:
    """Per-photo object masks and how far they can be trusted."""

    masks: dict[str, np.ndarray]
    """Frame name -> (h, w) bool at the photo's own size and pixels (lens distortion as in the photo)."""
    agreement: dict[str, float]
    """Frame name -> fraction of the photo's cut inside the silhouette of the hull the photos carve (those that frame
    the object, when close-ups crop it: FRAMED_SHARE)."""
    seed_recall: float
    """Fraction of the object's sparse-point sightings that fall inside the final masks."""
    edge_support: dict[str, float]
    """Frame name -> fraction of the mask's outline that lies on an edge of the photo."""
    confident: bool
    reason: str
    coverage: dict[str, float] = field(default_factory=dict)
    """Frame name -> fraction of the photo's pixels that are object."""
    astray: list[str] = field(default_factory=list)
    """The photos that show none of the object where SfM placed them (`ASTRAY_SHARE`): to be left out of training."""


PhotoLoader = Callable[[Frame], np.ndarray]


def object_on_background(scene: Scene, turntable: bool = False) -> bool:
    """An object capture whose photos show a lot of table and room: normalize contracted it around the object, or
    the photos were taken on a ``turntable`` (`recon.capture.turntable`), whose still room turns with the cameras in
    the object's frame, so no field can hold it."""
    return (scene.capture == "unbounded" or turntable) and scene.region is not None and not scene.has_alpha


@dataclass(frozen=True)
class _Cut:
    """One photo's first cut and what the later steps need of it, all at the cut's size."""

    mask: np.ndarray  # (h, w) bool
    edges: np.ndarray  # (h, w) bool: the photo's strong gradients, which a good outline follows
    intrinsics: np.ndarray  # (fx, fy, cx, cy) at (w, h)
    size: tuple[int, int]  # (w, h)
    seeds: np.ndarray  # (S, 2) pixels of the object points the cut started from
    grey: np.ndarray  # (h, w) uint8 pinhole image, for the table's cross-photo check
    judged: np.ndarray  # (J, 2) pixels of the seeds the recall counts (no lone points)
    judged_points: np.ndarray  # (J,) their indices in the scene's points
    frames_object: bool  # the object's box lies mostly in frame (not a close-up)
    background_seeds: int  # how many background points the cut started from


def segment_object(scene: Scene, load_photo: PhotoLoader | None = None, side: int = SEGMENT_SIDE,
                   progress: Callable[[], object] | None = None,
                   background: Callable[[Frame], np.ndarray | None] | None = None) -> ObjectMasks:
    """Segment the object region of a normalized scene in every photo (see the module docstring).

    scene: normalized, with `region` (2, 3) and sparse points with per-photo visibility; load_photo(frame) -> the
    photo as float (H, W, 3) in [0, 1] at any size with the frame's aspect (default: read from disk at `side`).
    background(frame) -> pixels known to be background ((h, w) bool at any size with the frame's aspect, e.g. a
    turntable's still room: `recon.capture.turntable`) or None: they seed the background and leave the cut.
    """
    import cv2

    from recon.nerf.device import cpu_threads

    if scene.region is None:
        raise ValueError("segment_object needs the scene's object region (normalize finds it for object captures)")
    load = load_photo or (lambda f: read_image(scene.image_path(f), max_side=side)[..., :3])
    points = np.asarray(scene.points, np.float64).reshape(-1, 3)
    region = cut_region(scene, points)
    extent = region[1] - region[0]
    grown = np.stack([region[0] - REGION_MARGIN * extent, region[1] + REGION_MARGIN * extent])
    object_pts, background_pts = _label_points(points, region, grown, scene.ground, scene.region_points,
                                               scene.aside_points)
    # on a wall, what lies between the object and the wall beside it is the wall, seen past the object
    on_ground = STANDS_ON_SUPPORT and scene.ground is not None and support_kind(scene.ground) == "ground"
    spread = _triangulation_spread(scene, points)  # photo pixels

    counted = ~_lone_points(points, object_pts)

    def certain(frame: Frame, w: int) -> np.ndarray:
        """The object points this photo's cut takes as seeds (P,) bool: those placed within SEED_SPREAD_PX."""
        return object_pts & (spread * (w / frame.w) <= SEED_SPREAD_PX)

    def cut_one(frame: Frame, hull: np.ndarray | None = None) -> _Cut:
        """The photo's cut; hull: the hull's (h, w) silhouette in it, for a close-up's second cut."""
        photo = np.asarray(load(frame), np.float32)[..., :3]
        h, w = photo.shape[:2]
        intr = np.array(frame.intrinsics_at(w, h))
        pinhole = undistort(photo, *intr, frame.distortion, frame.camera_model)
        seen = scene.point_visibility.get(frame.name)
        seen = np.arange(len(points)) if seen is None else np.asarray(seen, np.int64)
        # every object point lands inside the object's outline (the object hides its own back, not its outline);
        # background points only where the photo sees them (a hidden table point may lie behind the object)
        seeded = certain(frame, w)
        fg = _visible_uv(points[seeded], frame.c2w, intr, w, h)
        judged_points = np.flatnonzero(seeded & counted)  # the seeds the recall counts
        judged, in_view = _visible(points[judged_points], frame.c2w, intr, w, h)
        bg = _visible_uv(points[seen[background_pts[seen]]], frame.c2w, intr, w, h)
        feet = _visible_uv(_feet(points[seeded], scene.ground), frame.c2w, intr, w, h) if on_ground else None
        box_uv = _visible_uv(box_corners(grown), frame.c2w, intr, w, h, clip=False)
        known = background(frame) if background is not None else None
        if known is not None:
            known = cv2.resize(np.asarray(known, np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
            known = undistort(known, *intr, frame.distortion, frame.camera_model) > 0.5
        grey = np.round(np.clip(pinhole @ np.float32([0.299, 0.587, 0.114]), 0, 1) * 255).astype(np.uint8)
        frames_object = _framed_share(box_uv, w, h) >= FRAMED_SHARE
        cut = _grabcut(cv2, pinhole, fg, bg, box_uv, known, feet, hull)
        return _Cut(cut, _edges(cv2, pinhole), intr, (w, h), fg, grey, judged, judged_points[in_view], frames_object,
                    len(bg))

    cuts, intrinsics, sizes, seeds, edges, greys, framing, background_seeds = [], [], [], [], [], [], [], []
    judged_seeds, judged_points = [], []
    # one photo per core: OpenCV's graph cut runs on one thread and releases the GIL; each cut seeds its own
    # thread's RNG, so the masks do not depend on the thread count
    with ThreadPoolExecutor(max_workers=cpu_threads()) as pool:
        for one in pool.map(cut_one, scene.frames):  # kept as lists: the grey images are dropped once used
            cuts.append(one.mask)
            edges.append(one.edges)
            intrinsics.append(one.intrinsics)
            sizes.append(one.size)
            seeds.append(one.seeds)
            greys.append(one.grey)
            judged_seeds.append(one.judged)
            judged_points.append(one.judged_points)
            framing.append(one.frames_object)
            background_seeds.append(one.background_seeds)
            if progress is not None:
                progress()

    n = len(cuts)
    close_ups = [k for k in range(n) if not framing[k]]
    voters = framing if close_ups and n - len(close_ups) >= MIN_FRAMING_VOTERS else None
    silhouettes, _ = hull_silhouettes(grown, HULL_RES, [f.c2w for f in scene.frames], intrinsics, cuts, HULL_TOLERANCE,
                                      voters)
    recut, filled_by_hull = [], []
    if voters is not None:
        recut = [k for k in close_ups if (~silhouettes[k]).mean() >= MIN_HULL_BACKGROUND]
        filled_by_hull = [k for k in close_ups if k not in recut and background_seeds[k] < MIN_BACKGROUND_SEEDS]
        for k in filled_by_hull:
            cuts[k] = silhouettes[k].copy()
    under_cut = [k for k in undercut(cuts, silhouettes, framing) if (~silhouettes[k]).mean() >= MIN_HULL_BACKGROUND]
    if recut or under_cut:
        # each photo is read again rather than held from the first pass: a clip's frames would all stay in memory
        with ThreadPoolExecutor(max_workers=cpu_threads()) as pool:
            cut_again = recut + under_cut
            again = pool.map(lambda k: cut_one(scene.frames[k], silhouettes[k]).mask, cut_again)
            for k, cut in zip(cut_again, again, strict=True):
                cuts[k] = cut

    agreement, filled = {}, []
    for frame, cut, silhouette in zip(scene.frames, cuts, silhouettes, strict=True):
        agreed = cut & silhouette
        agreement[frame.name] = float(agreed.sum() / cut.sum()) if cut.any() else 0.0
        filled.append(_fill_agreed_holes(cv2, agreed, silhouette))
    table_dropped = bites_filled = 0  # photos whose masks each step changed by over a percent
    if on_ground and (DROP_TABLE or FILL_GROUNDED_BITES):
        c2ws = [f.c2w for f in scene.frames]
        on_table = _table_agreement(cv2, greys, c2ws, intrinsics, scene.ground, region, points[object_pts])
        del greys
        if DROP_TABLE:
            before, filled = filled, [_drop_table(cv2, mask, table >= TABLE_NCC, table <= -1, fg)
                                      for mask, table, fg in zip(filled, on_table, seeds, strict=True)]
            table_dropped = _changed(before, filled)
        if FILL_GROUNDED_BITES:
            before, filled = filled, _fill_grounded_bites(cv2, filled, silhouettes, c2ws, intrinsics, scene.ground,
                                                          max(1, int(HULL_TOLERANCE * n)),
                                                          [t < TABLE_NCC for t in on_table])
            bites_filled = _changed(before, filled)

    finals, support = [], {}
    sightings, kept_by = np.zeros(len(points), np.int64), np.zeros(len(points), np.int64)
    for frame, final, (w, h), judged, which, edge in zip(scene.frames, filled, sizes, judged_seeds, judged_points,
                                                         edges, strict=True):
        outline = _outline(cv2, final)
        support[frame.name] = float(edge[outline].mean()) if outline.any() else 0.0
        if len(judged):
            px = np.clip(judged.astype(np.int64), 0, [w - 1, h - 1])
            np.add.at(sightings, which, 1)
            np.add.at(kept_by, which, final[px[:, 1], px[:, 0]].astype(np.int64))
        finals.append(final)
    refuted = _refuted(sightings, kept_by)
    kept, total = int(kept_by[~refuted].sum()), int(sightings[~refuted].sum())
    with ThreadPoolExecutor(max_workers=cpu_threads()) as pool:  # full-size resampling: OpenCV, GIL released
        full = pool.map(lambda args: _to_photo_pixels(cv2, *args), zip(finals, scene.frames, intrinsics))
        masks = {frame.name: mask for frame, mask in zip(scene.frames, full, strict=True)}
    coverage = {name: float(mask.mean()) for name, mask in masks.items()}

    median = float(np.median(list(agreement.values()))) if agreement else 0.0
    recall = kept / total if total else 0.0
    worst = min(agreement, key=agreement.get) if agreement else ""
    empty = [name for name, c in coverage.items() if c <= 0.0]
    astray = _astray(scene, object_pts, empty)
    empty = [name for name in empty if name not in astray]
    on_edges = float(np.median(list(support.values()))) if support else 0.0
    confident = median >= MIN_AGREEMENT and recall >= MIN_SEED_RECALL and on_edges >= MIN_EDGE_SUPPORT and not empty
    lone = int(np.sum(object_pts & ~counted))
    uncounted = ([f"{lone} lone point(s) far from the others, false matches in the air"] if lone else []) + (
        [f"{int(refuted.sum())} point(s) that nearly every mask leaves out, false matches beside the object"]
        if refuted.any() else [])
    reason = (
        f"automatic object masks for {n} photos: the photos' cuts lie in the hull they carve together "
        f"(median {median:.0%}, least {agreement.get(worst, 0.0):.0%} in {worst}), keep {recall:.0%} of the "
        f"object's sparse points" + (f" ({'; '.join(uncounted)}: not counted)" if uncounted else "") +
        f" and their outlines follow the photos' edges ({on_edges:.0%})"
    )
    if on_ground:
        reason += "; each cut started from the object's points and their feet on the ground (it stands on it)"
    if voters is not None:
        reason += (f"; {len(close_ups)} close-up(s) crop the object, so only the {n - len(close_ups)} photos that "
                   "frame it carved the hull" + (f", and {len(recut)} close-up(s) were cut again inside its "
                                                 "silhouette, their background learnt outside it" if recut else "") +
                   (f"; {len(filled_by_hull)} close-up(s) lie within the hull's silhouette and show under "
                    f"{MIN_BACKGROUND_SEEDS} background points "
                    f"({', '.join(scene.frames[k].name for k in filled_by_hull)}): each mask is the silhouette"
                    if filled_by_hull else ""))
    if under_cut:
        reason += (f"; {len(under_cut)} photo(s) that frame it ({', '.join(scene.frames[k].name for k in under_cut)}) "
                   f"were cut again inside the hull's silhouette: their first cut left out over "
                   f"{MAX_HULL_MISSED:.0%} of it, which the other photos show as object")
    if astray:
        reason += (f"; {len(astray)} photo(s) ({', '.join(astray)}) show none of the object where SfM placed them "
                   f"(an empty mask, and under {ASTRAY_SHARE:.0%} of the object's sparse points the median photo "
                   "observes: misregistered on a few matches, or missing the object): left out of training")
    if table_dropped:
        reason += (f"; {table_dropped} photo(s) gave back table their cut had taken (its texture lines up with "
                   "the other photos' views of the table: a cast shadow)")
    if bites_filled:
        reason += (f"; {bites_filled} photo(s) got back a bite their cut had taken out of the object (its rays "
                   "meet the table where the other photos see the object)")
    if not confident:
        why = ([f"median {median:.0%} in the hull < {MIN_AGREEMENT:.0%}"] if median < MIN_AGREEMENT else []) + (
            [f"{recall:.0%} of the object's points kept < {MIN_SEED_RECALL:.0%}"] if recall < MIN_SEED_RECALL else []) + (
            [f"outlines on edges {on_edges:.0%} < {MIN_EDGE_SUPPORT:.0%}"] if on_edges < MIN_EDGE_SUPPORT else []) + (
            [f"{len(empty)} photo(s) with an empty mask"] if empty else [])
        reason += f" — not sure enough ({'; '.join(why)})"
    return ObjectMasks(masks, agreement, recall, support, confident, reason, coverage, astray)


def _astray(scene: Scene, object_pts: np.ndarray, empty: list[str]) -> list[str]:
    """Of the photos with an empty mask (names), those that observe under ASTRAY_SHARE of the object's sparse points
    (`object_pts` (P,) bool) the median photo does; none when they are over MAX_ASTRAY_SHARE of the photos, or when
    the scene does not say which photo observes which point."""
    if not empty or not scene.point_visibility:
        return []
    seen = {f.name: int(object_pts[np.asarray(scene.point_visibility.get(f.name, []), np.int64)].sum())
            for f in scene.frames}
    median = float(np.median(list(seen.values())))
    astray = [name for name in empty if seen[name] < ASTRAY_SHARE * median]
    return astray if len(astray) <= max(1, int(MAX_ASTRAY_SHARE * len(scene.frames))) else []


def undercut(cuts: list[np.ndarray], silhouettes: list[np.ndarray], framing: list[bool]) -> list[int]:
    """The photos (indices) that frame the object whose cut leaves out more than MAX_HULL_MISSED of the hull's
    silhouette in them: what the other photos all show as object. A close-up's cut misses what it crops."""
    picked = []
    for k, (cut, silhouette) in enumerate(zip(cuts, silhouettes, strict=True)):
        inside = int(silhouette.sum())
        if framing[k] and inside and (silhouette & ~cut).sum() > MAX_HULL_MISSED * inside:
            picked.append(k)
    return picked


def matte(mask: np.ndarray, photo: np.ndarray, radius: float = MATTE_RADIUS, eps: float = MATTE_EPS,
          contrast: float = MATTE_CONTRAST) -> np.ndarray:
    """(h, w) float32 in [0, 1]: the bool cut `mask` (h, w) with its outline moved onto the edges of `photo` (h, w, 3),
    float in [0, 1] at the same size, and soft across them as a photo's edge is (its pixels mix object and background).

    A cut made at `SEGMENT_SIDE` and grown to the photo's size is off by a pixel or two and hard; a guided filter
    (He et al., OpenCV's ximgproc) keeps the mask where the photo is flat and lets it follow the photo's own edges.
    """
    import cv2

    pixels = max(1, round(radius * max(mask.shape)))
    guide = np.ascontiguousarray(photo[..., :3], np.float32)
    soft = cv2.ximgproc.guidedFilter(guide, mask.astype(np.float32), pixels, eps)
    return np.clip((soft - 0.5) * contrast + 0.5, 0.0, 1.0).astype(np.float32)


def matte_photos(scene: Scene, masks: dict[str, np.ndarray],
                 progress: Callable[[], object] | None = None) -> dict[str, np.ndarray]:
    """`matte` of every frame's mask in `masks` (frame name -> bool at the photo's size) with its photo read from disk,
    as uint8 (0-255, the PNGs' own precision): every photo's matte held at once costs what its bool cut does."""
    from recon.nerf.device import cpu_threads

    frames = [f for f in scene.frames if f.name in masks]

    def one(frame: Frame) -> np.ndarray:
        soft = np.round(matte(masks[frame.name], read_image(scene.image_path(frame))) * 255).astype(np.uint8)
        if progress is not None:
            progress()
        return soft

    with ThreadPoolExecutor(max_workers=cpu_threads()) as pool:  # OpenCV's filter releases the GIL
        return {f.name: soft for f, soft in zip(frames, pool.map(one, frames), strict=True)}


def cut_region(scene: Scene, points: np.ndarray) -> np.ndarray:
    """(2, 3) the box the cuts look for the object in: the scene's region, grown to hold the sparse points (P, 3)
    normalize took for the object where it says which (`BOX_EVERY_OBJECT_POINT`)."""
    region = np.asarray(scene.region, np.float64)
    if not BOX_EVERY_OBJECT_POINT or scene.region_points is None:
        return region
    chosen = points[np.asarray(scene.region_points, bool) & np.all(np.isfinite(points), axis=1)]
    if not len(chosen):
        return region
    return np.stack([np.minimum(region[0], chosen.min(axis=0)), np.maximum(region[1], chosen.max(axis=0))])


def _label_points(points: np.ndarray, region: np.ndarray, grown: np.ndarray, ground: np.ndarray | None,
                  chosen: np.ndarray | None = None, aside: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(object (P,) bool, background (P,) bool): points inside the region and off the support plane (of those,
    only the ones normalize took for the object's, ``chosen``, where it says); points outside the grown region, on
    the plane, or left out as things beside the object (``aside``: a picture's corner inside the box of a head on
    the wall is no seed of the head). Points between the two boxes, and those in the box that normalize took for
    neither, are neither (unsure)."""
    finite = np.all(np.isfinite(points), axis=1)
    safe = np.where(finite[:, None], points, 0.0)
    inside = finite & np.all((safe >= region[0]) & (safe <= region[1]), axis=1)
    outside = finite & ~np.all((safe >= grown[0]) & (safe <= grown[1]), axis=1)
    on_plane = np.zeros(len(points), bool)
    if ground is not None:
        band = GROUND_BAND * float(np.max(region[1] - region[0]))
        height = safe @ np.asarray(ground[:3], np.float64) - float(ground[3])
        on_plane = finite & (height < band)
    obj = inside & ~on_plane & (True if chosen is None else np.asarray(chosen, bool))
    beside = np.zeros(len(points), bool) if aside is None else np.asarray(aside, bool) & finite
    return obj & ~beside, outside | on_plane | beside


def _lone_points(points: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """(P,) bool: the chosen points (P,) bool farther than LONE_POINT_SPACING times their median nearest-neighbour
    distance from every other chosen point."""
    from scipy.spatial import cKDTree

    lone = np.zeros(len(points), bool)
    idx = np.flatnonzero(chosen)
    if len(idx) < 3:
        return lone
    nearest = cKDTree(points[idx]).query(points[idx], k=2)[0][:, 1]
    lone[idx] = nearest > LONE_POINT_SPACING * max(float(np.median(nearest)), 1e-12)
    return lone


def _triangulation_spread(scene: Scene, points: np.ndarray) -> np.ndarray:
    """(P,) how far each point's triangulation may place it off its true position, seen across a view at its distance,
    in the photos' pixels (see SEED_SPREAD_PX); points without a reprojection error count MIN_KEYPOINT_ERROR_PX. A
    scene that does not say which photo observes which point (an import) gives no spread: every point is taken."""
    if not scene.point_visibility:
        return np.zeros(len(points))
    angles = triangulation_angles(points, np.array([f.c2w[:3, 3] for f in scene.frames]),
                                  [np.asarray(scene.point_visibility.get(f.name, ()), np.int64) for f in scene.frames])
    error = (np.zeros(len(points)) if scene.point_errors is None or len(scene.point_errors) != len(points)
             else np.asarray(scene.point_errors, np.float64).reshape(-1))
    floor = math.sin(math.radians(MIN_TRIANGULATION_DEG))
    return np.maximum(error, MIN_KEYPOINT_ERROR_PX) / np.maximum(np.sin(angles), floor)


def _refuted(sightings: np.ndarray, kept_by: np.ndarray) -> np.ndarray:
    """(P,) bool: the points at most REFUTED_KEPT of whose sightings (P,) the masks kept (kept_by (P,)), the most
    refuted first, no more than MAX_REFUTED of the points seen at all."""
    seen = np.flatnonzero(sightings > 0)
    share = kept_by[seen] / sightings[seen]
    order = np.argsort(share, kind="stable")
    picked = order[share[order] <= REFUTED_KEPT][: int(MAX_REFUTED * len(seen))]
    refuted = np.zeros(len(sightings), bool)
    refuted[seen[picked]] = True
    return refuted


def _visible(points: np.ndarray, c2w: np.ndarray, intr: np.ndarray, w: int, h: int,
             clip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) pixel coordinates of the points (P, 3) in front of the camera (and, with clip, inside the frame), and
    which of them those are, (P,) bool."""
    if not len(points):
        return np.zeros((0, 2)), np.zeros(0, bool)
    uv, z = project(points, c2w, intr)
    keep = z > 1e-9
    if clip:
        keep &= (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return uv[keep], keep


def _visible_uv(points: np.ndarray, c2w: np.ndarray, intr: np.ndarray, w: int, h: int, clip: bool = True) -> np.ndarray:
    """(M, 2) pixel coordinates of the points in front of the camera (and, with clip, inside the frame)."""
    return _visible(points, c2w, intr, w, h, clip)[0]


def _feet(points: np.ndarray, support: np.ndarray) -> np.ndarray:
    """(P, 3) the points dropped along the support plane's (4,) normal onto it."""
    n = np.asarray(support[:3], np.float64)
    return points - (points @ n - float(support[3]))[:, None] * n


def _grabcut(cv2, photo: np.ndarray, fg: np.ndarray, bg: np.ndarray, box_uv: np.ndarray,
             known_background: np.ndarray | None = None, feet: np.ndarray | None = None,
             hull: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool object pixels of one undistorted photo from its seeds (see the module docstring); `feet`: the
    object seeds dropped onto the support plane, whose hull with the seeds starts as probable object; `hull`: the
    (h, w) silhouette of the hull other photos carved, probable object inside and background outside (a close-up's
    second cut: FRAMED_SHARE)."""
    h, w = photo.shape[:2]
    label = np.full((h, w), cv2.GC_BGD, np.uint8)
    if len(box_uv) == 8:  # the whole grown box in front of the camera: outside its outline is background
        cv2.fillConvexPoly(label, cv2.convexHull(np.round(box_uv).astype(np.int32)), int(cv2.GC_PR_BGD))
    else:  # the camera is inside or beside the box: no pixel is sure background by the outline
        label[:] = cv2.GC_PR_BGD
    if len(fg) < 3:
        return np.zeros((h, w), bool)
    if hull is not None:
        label[hull] = cv2.GC_PR_FGD
        label[~hull] = cv2.GC_BGD
    seeds_hull = cv2.convexHull(np.round(fg if feet is None else np.concatenate([fg, feet])).astype(np.int32))
    cv2.fillConvexPoly(label, seeds_hull, int(cv2.GC_PR_FGD))
    radius = max(1, round(SEED_RADIUS * float(np.hypot(w, h))))
    if known_background is not None:
        label[known_background] = cv2.GC_BGD
    for u, v in np.round(bg).astype(np.int32):
        cv2.circle(label, (int(u), int(v)), radius, int(cv2.GC_BGD), -1)
    px = np.clip(np.round(fg).astype(np.int64), 0, [w - 1, h - 1])
    label[px[:, 1], px[:, 0]] = cv2.GC_FGD  # each object point its own pixel (SEED_RADIUS)
    image = np.round(np.clip(photo, 0, 1) * 255).astype(np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    cv2.grabCut(image, label, None, bgd, fgd, 5, cv2.GC_INIT_WITH_MASK)
    cut = (label == cv2.GC_FGD) | (label == cv2.GC_PR_FGD)
    if known_background is not None:
        cut &= ~known_background
    return _keep_seeded_pieces(cv2, cut, fg)


def _framed_share(box_uv: np.ndarray, w: int, h: int) -> float:
    """The share of the box's projected outline (box_uv: its 8 corners' pixels, fewer when some are behind the camera)
    that lies inside the w × h photo (see FRAMED_SHARE); 0 when the camera is inside or beside the box."""
    import cv2

    if len(box_uv) < 8:
        return 0.0
    outline = cv2.convexHull(np.asarray(box_uv, np.float32))
    area = float(cv2.contourArea(outline))
    if area <= 0.0:
        return 0.0
    photo = np.float32([[0, 0], [w, 0], [w, h], [0, h]]).reshape(-1, 1, 2)
    inside, _ = cv2.intersectConvexConvex(outline, photo)
    return float(inside) / area


def _keep_seeded_pieces(cv2, cut: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """The connected pieces of the cut that hold an object seed, with pinholes (enclosed specks under
    MAX_SPECK of the photo) filled; larger enclosed background — a handle's opening — stays background."""
    _, labels, pieces, _ = cv2.connectedComponentsWithStats(cut.astype(np.uint8), connectivity=8)
    h, w = cut.shape
    px = np.clip(np.round(fg).astype(np.int64), 0, [w - 1, h - 1])
    seeded = np.unique(labels[px[:, 1], px[:, 0]])
    seeded = seeded[seeded > 0]
    if len(seeded):  # a stray point's lone seed is no piece of the object
        area = pieces[seeded, cv2.CC_STAT_AREA]
        seeded = seeded[area >= MIN_PIECE * area.max()]
    keep = np.isin(labels, seeded)
    return _fill_holes(cv2, keep, lambda holes, stats: np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < MAX_SPECK * h * w))


def _fill_holes(cv2, mask: np.ndarray, pick: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """The mask with the background pieces it encloses (4-connected, off the photo's border) filled where
    ``pick(labels, stats)`` names their labels (OpenCV's connected-component labels and stats of ~mask)."""
    _, holes, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([holes[0], holes[-1], holes[:, 0], holes[:, -1]]))
    return mask | np.isin(holes, np.setdiff1d(pick(holes, stats), border))


def _fill_agreed_holes(cv2, mask: np.ndarray, silhouette: np.ndarray) -> np.ndarray:
    """The mask with each hole it encloses filled when (almost, ``HOLE_IN_HULL``) all of it lies in the silhouette of
    the hull the photos carve: a graph cut leaves holes in fur, dark or glossy patches that no other photo confirms.
    An opening the photos see through (a handle's, a torus's) is carved out of the hull; where few photos see through
    it the carved tunnel is narrower than the opening this photo shows, but it still leaves part of the hole outside
    the silhouette, so the whole opening stays background (filling it wherever the hull was solid cost the realistic
    tabletop's torus its opening)."""
    def in_hull(holes: np.ndarray, stats: np.ndarray) -> np.ndarray:
        inside = np.bincount(holes[silhouette], minlength=len(stats))
        return np.flatnonzero(inside >= HOLE_IN_HULL * stats[:, cv2.CC_STAT_AREA])

    return _fill_holes(cv2, mask, in_hull)


def _fill_grounded_bites(cv2, masks: list[np.ndarray], silhouettes: list[np.ndarray], c2ws: list[np.ndarray],
                         intrinsics: list[np.ndarray], ground: np.ndarray, allowed: int,
                         off_table: list[np.ndarray]) -> list[np.ndarray]:
    """Each mask with the pixels of its hull silhouette beside it whose rays reach the support plane (4,) where at
    most `allowed` of the other photos' masks show table.

    Why: a graph cut gives a plain or shadowed base the table's colour model, and one photo's bite carves the base
    out of the field. The hull cannot tell such a bite from space the other photos merely fail to carve (it is fatter
    than the object wherever no photo looks edge-on), but where the ray goes on to meet the table tells them apart:
    past a bitten base it meets the table under the object, which every other photo sees covered by the object;
    past the object's side or under a raised base it meets table that other photos see bare. Only pixels that do not
    show the table (`off_table`, per photo (h, w) bool) are given back: a cast shadow in front of the base meets the
    table where the photos whose cuts took the shadow for object show none."""
    n = len(masks)
    normal, offset = np.asarray(ground[:3], np.float64), float(ground[3])
    min_views = max(2, math.ceil(MIN_GROUND_VIEWS * (n - 1)))
    ring = np.ones((3, 3), np.uint8)
    out = []
    for k, (mask, sil) in enumerate(zip(masks, silhouettes, strict=True)):
        rows, cols = np.nonzero(sil & ~mask & off_table[k])
        if not len(rows) or not mask.any():
            out.append(mask)
            continue
        fx, fy, cx, cy = intrinsics[k]
        o, d = pixel_rays(np.asarray(c2ws[k], np.float64), fx, fy, cx, cy, cols + 0.5, rows + 0.5)
        towards = d @ normal  # the plane's normal points at the object: rays to the table run against it
        t = np.where(towards < -1e-9, (offset - o @ normal) / np.where(towards < -1e-9, towards, -1.0), -1.0)
        table = o + np.maximum(t, 0.0)[:, None] * d
        seen_by, bare_in = np.zeros(len(rows), np.int32), np.zeros(len(rows), np.int32)
        for j in range(n):
            if j == k:
                continue
            h, w = masks[j].shape
            uv, z = project(table, np.asarray(c2ws[j], np.float64), intrinsics[j])
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            seen = (t > 0) & (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            seen_by += seen
            bare_in[seen] += ~masks[j][row[seen], col[seen]]
        grounded = np.zeros_like(mask)
        grounded[rows, cols] = (seen_by >= min_views) & (bare_in <= allowed)
        _, pieces = cv2.connectedComponents(grounded.astype(np.uint8), connectivity=8)
        beside = np.unique(pieces[(cv2.dilate(mask.astype(np.uint8), ring) > 0) & grounded])
        out.append(mask | np.isin(pieces, beside[beside > 0]))
    return out


def _changed(before: list[np.ndarray], after: list[np.ndarray]) -> int:
    """How many masks changed by more than a percent of their pixels."""
    return sum(int((a != b).sum() > 0.01 * max(int(a.sum()), 1)) for a, b in zip(before, after, strict=True))


def _table_agreement(cv2, greys: list[np.ndarray], c2ws: list[np.ndarray], intrinsics: list[np.ndarray],
                     ground: np.ndarray, region: np.ndarray, object_points: np.ndarray) -> list[np.ndarray]:
    """Per photo, (h, w) float32: how well each pixel's window matches, in the second best of its `TABLE_PARTNERS`,
    the partner's view of the support plane (4,) there (normalized cross-correlation of grey levels, the partner
    warped onto this photo by the plane's homography); -1 where either window is flat or the partner does not see it.
    Partners: see `TABLE_PARTNERS`; the parallax is measured on the `object_points` (M, 3) (on the region's corners
    when there are none).

    Why: the table is the one surface every photo sees through the same homography, so its texture lines up across
    photos, lit or in the object's shadow (colour models cannot tell a cast shadow from a dark base); the object, off
    the plane, lines up only where it touches it. Correlation ignores each photo's exposure and white balance."""
    normal, offset = np.asarray(ground[:3], np.float64), float(ground[3])
    centre = region.mean(axis=0)
    centre = centre - (centre @ normal - offset) * normal
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    size = float(np.max(region[1] - region[0]))
    square = centre + size * np.array([u + v, u - v, -u - v, -u + v])  # four points on the plane
    views = [(np.asarray(c2w, np.float64), np.asarray(intr, np.float64)) for c2w, intr in zip(c2ws, intrinsics)]
    corners = [project(square, c2w, intr) for c2w, intr in views]
    seen_from = np.array([c2w[:3, 3] - region.mean(axis=0) for c2w, _ in views])
    seen_from /= np.maximum(np.linalg.norm(seen_from, axis=1, keepdims=True), 1e-12)
    marks = object_points if len(object_points) else box_corners(region)
    marks = marks[:: max(1, len(marks) // PARALLAX_POINTS)]
    seen = [project(marks, c2w, intr) for c2w, intr in views]
    out = []
    for k, grey in enumerate(greys):
        h, w = grey.shape
        side = _table_window(h, w)
        a = grey.astype(np.float32)
        mean_a = cv2.boxFilter(a, -1, (side, side))
        var_a = cv2.boxFilter(a * a, -1, (side, side)) - mean_a**2
        homographies = {}
        for j in range(len(greys)):
            (uv_k, z_k), (uv_j, z_j) = corners[k], corners[j]
            if j != k and np.all(z_k > 0) and np.all(z_j > 0) \
                    and seen_from[j] @ seen_from[k] >= math.cos(math.radians(MAX_TABLE_TURN)):
                homographies[j] = cv2.getPerspectiveTransform(uv_k.astype(np.float32), uv_j.astype(np.float32))
        parallax = {j: _parallax(cv2, hom, seen[k], seen[j]) / side for j, hom in homographies.items()}
        scores = []
        for j in _table_partners(parallax):
            homography = homographies[j]
            b = cv2.warpPerspective(greys[j].astype(np.float32), homography, (w, h),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=-1.0)
            inside = cv2.erode((b >= 0).astype(np.uint8), np.ones((side, side), np.uint8)) > 0
            b = np.maximum(b, 0.0)
            mean_b = cv2.boxFilter(b, -1, (side, side))
            var_b = cv2.boxFilter(b * b, -1, (side, side)) - mean_b**2
            cov = cv2.boxFilter(a * b, -1, (side, side)) - mean_a * mean_b
            textured = (var_a >= TABLE_TEXTURE**2) & (var_b >= TABLE_TEXTURE**2) & inside
            scores.append(np.where(textured, cov / np.sqrt(np.maximum(var_a * var_b, 1e-6)), -1.0))
        if len(scores) < 2:
            out.append(np.full((h, w), -1.0, np.float32))
            continue
        out.append(np.sort(np.stack(scores), axis=0)[-2].astype(np.float32))  # the second best: two partners agree
    return out


def _table_partners(parallax: dict[int, float]) -> list[int]:
    """The `TABLE_PARTNERS` photos whose parallax (photo index -> windows; the photos within `MAX_TABLE_TURN`) is nearest
    `TABLE_PARALLAX` and at least `MIN_TABLE_PARALLAX`."""
    fit = [(abs(math.log(p / TABLE_PARALLAX)), j) for j, p in parallax.items() if p >= max(MIN_TABLE_PARALLAX, 1e-9)]
    return [j for _, j in sorted(fit)[:TABLE_PARTNERS]]


def _parallax(cv2, homography: np.ndarray, seen_here: tuple[np.ndarray, np.ndarray],
              seen_there: tuple[np.ndarray, np.ndarray]) -> float:
    """The median distance (pixels of the partner) between where the partner sees points and where the plane's
    `homography` (3, 3) puts them from this photo; `seen_*`: `project`'s (uv (M, 2), depth (M,)); 0 if none is in
    front of both cameras."""
    (here, z_here), (there, z_there) = seen_here, seen_there
    front = (z_here > 0) & (z_there > 0)
    if not front.any():
        return 0.0
    moved = cv2.perspectiveTransform(here[front][None].astype(np.float64), homography)[0]
    return float(np.median(np.linalg.norm(moved - there[front], axis=1)))


def _table_window(h: int, w: int) -> int:
    """The side (pixels, odd) of `_table_agreement`'s windows in an (h, w) photo."""
    return 2 * max(MIN_TABLE_HALF_WINDOW, round(0.5 * TABLE_WINDOW * max(h, w))) + 1


def _drop_table(cv2, mask: np.ndarray, table: np.ndarray, flat: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """The mask without the pixels that show the table (`table`, (h, w) bool): the table's pixels closed over the
    `flat` specks among them (too little texture to match: a shadow's darkest), then eroded by a window (one that
    straddles the outline matches as table, and specks of the object that match by chance do not pierce it), and the
    mask kept to its seeded pieces (`_keep_seeded_pieces`)."""
    h, w = mask.shape
    reach = _table_window(h, w)  # a window that straddles the outline correlates as the table's
    window = np.ones((reach, reach), np.uint8)
    closed = table | (flat & (cv2.morphologyEx(table.astype(np.uint8), cv2.MORPH_CLOSE, window) > 0))
    drop = mask & (cv2.erode(closed.astype(np.uint8), window) > 0)
    if not drop.any():
        return mask
    return _keep_seeded_pieces(cv2, mask & ~drop, fg)


def _edges(cv2, photo: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels whose Lab colour gradient is in the photo's top (100 - EDGE_PERCENTILE) percent."""
    lab = cv2.cvtColor(np.clip(photo, 0, 1).astype(np.float32), cv2.COLOR_RGB2LAB)
    gx, gy = cv2.Sobel(lab, cv2.CV_32F, 1, 0), cv2.Sobel(lab, cv2.CV_32F, 0, 1)
    grad = np.sqrt((gx**2 + gy**2).sum(axis=-1))
    return grad > np.percentile(grad, EDGE_PERCENTILE)


def _outline(cv2, mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels on either side of the mask's boundary."""
    m = mask.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    return (cv2.dilate(m, kernel) - cv2.erode(m, kernel)) > 0


def _to_photo_pixels(cv2, mask: np.ndarray, frame: Frame, intr: np.ndarray) -> np.ndarray:
    """A mask in the undistorted segmentation image, resampled onto the photo's own (distorted) full-size pixels."""
    h, w = mask.shape
    soft = mask.astype(np.float32)
    if not any(abs(d) > 0 for d in frame.distortion) and frame.camera_model != "OPENCV_FISHEYE":
        return cv2.resize(soft, (frame.w, frame.h), interpolation=cv2.INTER_LINEAR) >= 0.5
    # where each photo pixel lands in the pinhole image: undistort the pixel grid (at full size), then scale
    u, v = pixel_centres(frame.w, frame.h)
    K = intrinsic_matrix(frame.fl_x, frame.fl_y, frame.cx, frame.cy)
    pts = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :]
    if frame.camera_model == "OPENCV_FISHEYE":
        flat = cv2.fisheye.undistortPoints(pts, K, np.asarray(frame.distortion, np.float64), P=K)
    else:
        flat = cv2.undistortPoints(pts, K, np.asarray(frame.distortion, np.float64), P=K)
    flat = flat.reshape(frame.h, frame.w, 2)
    map_x = (flat[..., 0] * w / frame.w - 0.5).astype(np.float32)
    map_y = (flat[..., 1] * h / frame.h - 0.5).astype(np.float32)
    # a barrel lens's corners see past the pinhole image's edge: what the cut shows at its edge goes on beyond it (a
    # close-up's object does not stop a pixel short of the photo's border)
    return cv2.remap(soft, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) >= 0.5
