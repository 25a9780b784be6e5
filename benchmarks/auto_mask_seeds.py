"""What limits the automatic masks of a capture: its object region, its seeds, or the cut.

    python benchmarks/auto_mask_seeds.py SCENE [TRUE_MASKS] --name NAME

SCENE: a scene with recon's poses (`recon run PHOTOS --out SCENE --until poses`, or a `recon bench` scene's `*-poses`
folder), normalized here from its `01_poses` as the normalize stage does before it cuts; TRUE_MASKS: the generator's
true object masks, named like the photos (gen_tabletop.py's `capture/masks/`, gen_video.py's `masks/`; a real capture
without them, e.g. the fox, gets no IoU and no oracles).
Cuts the object out of every photo again (`segment_object`) as shipped, from another object region and with its seeds
changed, and scores each against the true masks: IoU per photo (median, least), the share of the true mask's lowest
fifth each leaves out (median, most: `missed_at_base`), how much of the outline lies on the photo's edges (the median
photo's: what `MIN_EDGE_SUPPORT` judges), how much of the median photo's cut lies in the hull (what `MIN_AGREEMENT`
judges), how far the outline lies outside and inside the true one (pixels along it, median photo; with `--mattes`
also the matte's) and whether the masks would be trusted; and how many sparse points the object region holds, with and
without the points linked to the in-frame ones (what close-ups leave out of frame). Variants:

- shipped: as normalize runs it (object seeds: the points SfM placed within `SEED_SPREAD_PX`, each its own pixel);
- no grounded bites: shipped, but no cut is given back the silhouette pixels beside it whose rays meet the table
  where the other photos show none (`FILL_GROUNDED_BITES`);
- no table drop: shipped, but the cut pixels whose texture lines up with the other photos' views of the table stay
  (`DROP_TABLE`); neither: without both (the masks before they came);
- lone points counted: shipped, but the object points far from every other one count in the share of points the masks
  keep (`LONE_POINT_SPACING`), which says whether they are trusted;
- refuted points counted: shipped, but the object points nearly every mask leaves out count in that share too
  (`MAX_REFUTED` = 0: the trust before such points were excused);
- least parallax: shipped, but each photo's table is matched with the photos that see the object's points move
  nearest `MIN_TABLE_PARALLAX` windows off the plane's homography (not `TABLE_PARALLAX`);
- close-ups vote: shipped, but every photo carves the hull, close-ups that crop the object too, and none is cut again
  inside it (`FRAMED_SHARE` = 0: the masks before close-ups were told apart);
- filled close-ups keep their cut: shipped, but a close-up that the hull's silhouette fills and that has no background
  points keeps its first cut rather than taking the silhouette (`MIN_BACKGROUND_SEEDS` = 0: the masks before);
- short cuts kept: shipped, but a photo that frames the object keeps its first cut even when it left out much of the
  hull's silhouette (`MAX_HULL_MISSED` = 1: the masks before such photos were cut again);
- no support prior: shipped, but the cut starts with the object seeds' hull alone as probable object, not their
  hull with their feet on the support plane (`STANDS_ON_SUPPORT`);
- in-frame region: the object region of only the points most photos keep in frame, without the points linked to
  them (`recon.capture.region.LINK_SPACINGS` = 0): the region before those links;
- box seeds: shipped, but every point inside the object region's box (off the support) seeds the object, and the
  points normalize left beside it seed nothing (`Scene.region_points` and `aside_points` unset: the seeds before
  normalize kept which points it took for the object's);
- every point, seed discs: the seeds before `SEED_SPREAD_PX` (every object point seeds a disc of `SEED_RADIUS`, as
  the background points do);
- hull tolerance T: shipped, but a hull vertex survives while at most the share T of the photos call it background
  (`HULL_TOLERANCE`; any T, e.g. "hull tolerance 0.1");
- region margin M: shipped, but the cut's box (outside its projection every pixel is background) is the object
  region grown by the share M of its size a side (`REGION_MARGIN`; any M, e.g. "region margin 0.3");
- region box: shipped, but the cut's box is the scene's object region alone, not grown to hold every point normalize
  took for the object (`BOX_EVERY_OBJECT_POINT`: the box before a thin part's few points apart from the rest counted);
- true object seeds: shipped, with the object seeds that fall outside the true mask dropped (an oracle);
- true seeds and a background ring: also 150 background seeds 3-4 px outside the true mask (an oracle).

With --write-masks DIR, each variant's masks are also written as normalize writes them (matted PNGs, white =
object) to DIR/<variant, spaces as underscores>/, for `mask_swap.py --masks`.
Writes benchmarks/results/NAME.json with the commit, machine, load and why normalize chose the object region. It
measures; it asserts nothing.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one

RING_SEEDS = 150


def missed_at_base(mask: np.ndarray, truth: np.ndarray) -> float:
    """The share of the true mask's lowest fifth (of its rows) that the mask leaves out: a plain or shadowed base given
    to the table bites there, and one photo's bite carves the field."""
    rows = np.flatnonzero(truth.any(axis=1))
    if not len(rows):
        return 0.0
    base = truth.copy()
    base[: rows[-1] - (rows[-1] - rows[0]) // 5] = False
    return float((base & ~mask).sum() / max(base.sum(), 1))


def outline_offset_px(mask: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """How far the mask's outline lies outside the true one, in pixels along the true outline: (extra, missed), the
    pixels the mask adds and leaves out, each over the true outline's length. A cut that is one pixel too fat all
    round gives (1, 0); a field trained on it grows a skin that thick at every silhouette."""
    import cv2

    contours, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    length = max(sum(cv2.arcLength(c, True) for c in contours), 1.0)
    return float((mask & ~truth).sum() / length), float((truth & ~mask).sum() / length)


def _is_share(text: str) -> bool:
    """Whether `text` (the T of a "hull tolerance T" variant) is a share of the photos, 0 <= T < 1."""
    try:
        return 0.0 <= float(text) < 1.0
    except ValueError:
        return False


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("true_masks", type=Path, nargs="?")
    ap.add_argument("--name", required=True, help="the record's name: benchmarks/results/NAME.json")
    ap.add_argument("--variants", default="", help="comma-separated variants to run (default: all)")
    ap.add_argument("--write-masks", type=Path, help="also write each variant's masks, matted as normalize writes "
                    "them, to DIR/<variant>/<photo stem>.png (for mask_swap.py --masks)")
    ap.add_argument("--mattes", action="store_true", help="also score the matted masks the train stage reads "
                    "(their outline at half opacity)")
    a = ap.parse_args(argv)

    import cv2

    from recon.app.bench import provenance
    from recon.atomic import write_json_atomic
    from recon.capture import auto_masks as am
    from recon.capture.images import read_image, save_image
    from recon.capture import region as object_region
    from recon.capture.normalization import normalize
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.config import NormalizeConfig

    source = load_scene(a.scene / "01_poses", recorded_source(a.scene))
    scene = normalize(source, NormalizeConfig())
    links = object_region.LINK_SPACINGS
    object_region.LINK_SPACINGS = 0.0
    try:
        in_frame = normalize(source, NormalizeConfig())
    finally:
        object_region.LINK_SPACINGS = links
    where = provenance()
    load_start = [round(x, 2) for x in os.getloadavg()]
    truth_of: dict[str, np.ndarray] = {}

    def true_mask(frame, w: int, h: int) -> np.ndarray:
        """The true mask at (w, h), in the photo's own (distorted) pixels."""
        t = cv2.imread(str(a.true_masks / f"{Path(frame.name).stem}.png"), cv2.IMREAD_GRAYSCALE)
        if t is None:
            raise SystemExit(f"no true mask for {frame.name} in {a.true_masks}")
        return cv2.resize(t, (w, h), interpolation=cv2.INTER_AREA) > 127

    def load(frame) -> np.ndarray:  # the photo as segment_object reads it; its undistorted true mask on the side
        photo = read_image(scene.image_path(frame), max_side=am.SEGMENT_SIDE)[..., :3]
        h, w = photo.shape[:2]
        intr = np.array(frame.intrinsics_at(w, h))
        if a.true_masks is not None:
            t = true_mask(frame, w, h).astype(np.float32)[..., None].repeat(3, axis=-1)
            truth_of[frame.name] = am.undistort(t, *intr, frame.distortion, frame.camera_model)[..., 0] > 0.5
        return photo

    original_grabcut, original_spread = am._grabcut, am._triangulation_spread
    filling, dropping, lone_spacing = am.FILL_GROUNDED_BITES, am.DROP_TABLE, am.LONE_POINT_SPACING
    max_refuted = am.MAX_REFUTED
    parallax, framed_share, max_missed = am.TABLE_PARALLAX, am.FRAMED_SHARE, am.MAX_HULL_MISSED
    background_seeds, tolerance, margin = am.MIN_BACKGROUND_SEEDS, am.HULL_TOLERANCE, am.REGION_MARGIN
    every_point = am.BOX_EVERY_OBJECT_POINT
    current: dict[str, str] = {}

    def variant(name: str, scene: Any = scene) -> dict[str, Any]:
        def spread(scene_, points_):
            return np.zeros(len(points_)) if name == "every point, seed discs" else original_spread(scene_, points_)

        def grabcut(cv2_, photo, fg, bg, box_uv, known=None, feet=None, hull=None):
            h, w = photo.shape[:2]
            if name == "every point, seed discs":  # each seed grown to a disc of SEED_RADIUS
                radius = max(1, round(am.SEED_RADIUS * float(np.hypot(w, h))))
                dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
                disc = np.stack([dx[dx**2 + dy**2 <= radius**2], dy[dx**2 + dy**2 <= radius**2]], axis=1)
                fg = (np.round(fg)[:, None, :] + disc[None]).reshape(-1, 2)
                fg = fg[(fg[:, 0] >= 0) & (fg[:, 0] < w) & (fg[:, 1] >= 0) & (fg[:, 1] < h)]
            if name.startswith("true"):
                t = truth_of[current["frame"]]
                px = np.clip(np.round(fg).astype(np.int64), 0, [w - 1, h - 1])
                fg = fg[t[px[:, 1], px[:, 0]]]
            if name == "true seeds and a background ring":
                near = cv2.dilate(t.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
                ring = (cv2.dilate(t.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0) & ~near
                ys, xs = np.nonzero(ring)
                pick = np.random.default_rng(0).choice(len(ys), min(len(ys), RING_SEEDS), replace=False)
                bg = np.concatenate([bg, np.stack([xs[pick], ys[pick]], axis=1)])
            if name == "no support prior":  # the cut's probable object: the seeds' hull alone, not their feet's too
                feet = None
            return original_grabcut(cv2_, photo, fg, bg, box_uv, known, feet, hull)

        def loader(frame):
            current["frame"] = frame.name
            return load(frame)

        am._triangulation_spread, am._grabcut = spread, grabcut
        am.FILL_GROUNDED_BITES = name not in ("no grounded bites", "neither")
        am.DROP_TABLE = name not in ("no table drop", "neither")
        am.LONE_POINT_SPACING = np.inf if name == "lone points counted" else lone_spacing
        am.MAX_REFUTED = 0.0 if name == "refuted points counted" else max_refuted
        am.TABLE_PARALLAX = am.MIN_TABLE_PARALLAX if name == "least parallax" else parallax
        am.FRAMED_SHARE = 0.0 if name == "close-ups vote" else framed_share
        am.MAX_HULL_MISSED = 1.0 if name == "short cuts kept" else max_missed
        am.MIN_BACKGROUND_SEEDS = 0 if name == "filled close-ups keep their cut" else background_seeds
        am.HULL_TOLERANCE = float(name.removeprefix("hull tolerance ")) if name.startswith("hull tolerance ") else tolerance
        am.REGION_MARGIN = float(name.removeprefix("region margin ")) if name.startswith("region margin ") else margin
        am.BOX_EVERY_OBJECT_POINT = name != "region box"
        import recon.nerf.device as device

        threads: Callable[[], int] = device.cpu_threads
        device.cpu_threads = lambda: 1  # one photo at a time: the oracle reads the current photo's truth
        clock = time.perf_counter()
        try:
            found = am.segment_object(scene, load_photo=loader)
        finally:
            am._triangulation_spread, am._grabcut, device.cpu_threads = original_spread, original_grabcut, threads
            am.FILL_GROUNDED_BITES, am.DROP_TABLE, am.LONE_POINT_SPACING = filling, dropping, lone_spacing
            am.MAX_REFUTED = max_refuted
            am.TABLE_PARALLAX, am.FRAMED_SHARE, am.MAX_HULL_MISSED = parallax, framed_share, max_missed
            am.MIN_BACKGROUND_SEEDS, am.HULL_TOLERANCE, am.REGION_MARGIN = background_seeds, tolerance, margin
            am.BOX_EVERY_OBJECT_POINT = every_point
        if a.write_masks is not None:
            folder = a.write_masks / name.replace(" ", "_").replace(",", "")
            folder.mkdir(parents=True, exist_ok=True)
            for frame_name, soft in am.matte_photos(scene, found.masks).items():
                save_image(folder / f"{Path(frame_name).stem}.png", (soft.astype(np.float32) / 255.0)[..., None])
        ious, base_missed, offsets, matte_offsets = [], {}, [], []
        mattes = am.matte_photos(scene, found.masks) if a.true_masks is not None and a.mattes else {}
        for frame in scene.frames if a.true_masks is not None else ():
            mask = found.masks[frame.name]
            t = true_mask(frame, mask.shape[1], mask.shape[0])
            ious.append(float((mask & t).sum() / max((mask | t).sum(), 1)))
            base_missed[frame.name] = missed_at_base(mask, t)
            offsets.append(outline_offset_px(mask, t))
            if frame.name in mattes:  # what the train stage reads: the matte, half opaque at its outline
                matte_offsets.append(outline_offset_px(mattes[frame.name] >= 128, t))

        def offset(rows: list[tuple[float, float]], k: int) -> float | None:
            return round(float(np.median([r[k] for r in rows])), 3) if rows else None
        worst = max(base_missed, key=base_missed.get) if base_missed else None
        row = {"variant": name,
               "iou_median": round(float(np.median(ious)), 4) if ious else None,
               "iou_least": round(min(ious), 4) if ious else None,
               "base_missed_median": round(float(np.median(list(base_missed.values()))), 4) if base_missed else None,
               "base_missed_most": round(base_missed[worst], 4) if worst else None, "base_missed_most_photo": worst,
               "iou_mean": round(float(np.mean(ious)), 4) if ious else None,
               "outline_extra_px_median": offset(offsets, 0), "outline_missed_px_median": offset(offsets, 1),
               "matte_outline_extra_px_median": offset(matte_offsets, 0),
               "matte_outline_missed_px_median": offset(matte_offsets, 1),
               "iou_by_photo": {f.name: round(x, 4) for f, x in zip(scene.frames, ious)} if ious else None,
               "seed_recall": round(float(found.seed_recall), 4),
               "agreement_median": round(float(np.median(list(found.agreement.values()))), 4),
               "edge_support_median": round(float(np.median(list(found.edge_support.values()))), 4),
               "confident": bool(found.confident), "reason": found.reason,
               "seconds": round(time.perf_counter() - clock, 1)}
        iou = (f"IoU median {row['iou_median']:.3f} (least {row['iou_least']:.3f}), outline "
               f"+{row['outline_extra_px_median']:.2f} / -{row['outline_missed_px_median']:.2f} px, " if ious else "")
        print(f"{name}: {iou}cut in the hull {row['agreement_median']:.0%}, outline on edges "
              f"{row['edge_support_median']:.0%}, {'trusted' if row['confident'] else 'not trusted'}", flush=True)
        return row

    oracles = ("true object seeds", "true seeds and a background ring") if a.true_masks is not None else ()
    names = ("shipped", "no grounded bites", "no table drop", "neither", "lone points counted",
             "refuted points counted", "least parallax", "close-ups vote", "filled close-ups keep their cut",
             "short cuts kept", "no support prior", "in-frame region", "box seeds", "region box",
             "every point, seed discs", *oracles)
    chosen = a.variants.split(",") if a.variants else names
    tolerances = [v for v in chosen if v.startswith("hull tolerance ")]
    margins = [v for v in chosen if v.startswith("region margin ")]
    if unknown := set(chosen) - set(names) - {v for v in tolerances if _is_share(v.removeprefix("hull tolerance "))} \
            - {v for v in margins if _is_share(v.removeprefix("region margin "))}:
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {', '.join(names)}, hull tolerance T, "
                         "region margin M (0 <= T, M < 1)")
    boxed = replace(scene, region_points=None, aside_points=None)
    rows = [variant(v, in_frame if v == "in-frame region" else boxed if v == "box seeds" else scene)
            for v in names if v in chosen]
    rows += [variant(v) for v in tolerances + margins]

    def object_points(scene: Any) -> np.ndarray:
        """(N,) bool: the sparse points the cut takes for object seeds (the object's, inside its cut's box)."""
        points = np.asarray(scene.points, np.float64).reshape(-1, 3)
        region = am.cut_region(scene, points)
        extent = region[1] - region[0]
        grown = np.stack([region[0] - am.REGION_MARGIN * extent, region[1] + am.REGION_MARGIN * extent])
        return am._label_points(points, region, grown, scene.ground, scene.region_points, scene.aside_points)[0]

    points = np.asarray(scene.points, np.float64).reshape(-1, 3)
    obj = object_points(scene)
    first = scene.frames[0]
    certain = original_spread(scene, points) * (min(am.SEGMENT_SIDE, max(first.w, first.h)) / max(first.w, first.h)) \
        <= am.SEED_SPREAD_PX
    record = {
        "scene": str(a.scene), "true_masks": str(a.true_masks) if a.true_masks else None,
        "photos": len(scene.frames), "region": scene.notes.get("region"), **where,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "load_average_start": load_start, "load_average_end": [round(x, 2) for x in os.getloadavg()],
        "object_points": int(obj.sum()), "object_points_certain": int((obj & certain).sum()),
        "object_points_in_frame_region": int(object_points(in_frame).sum()),
        "variants": rows,
    }
    out = REPO / "benchmarks" / "results" / f"{a.name}.json"
    write_json_atomic(out, [record])  # a record is a list of rows
    print(f"record: {out}")


if __name__ == "__main__":
    main()
