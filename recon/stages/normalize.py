"""normalize stage: the canonical scene (upright, centred, scaled), near/far per camera, the data split, and — for an
object photographed without masks in front of its table and room — the object's masks cut from the photos."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from recon.capture.auto_masks import HULL_RES, SEGMENT_SIDE, matte_photos, object_on_background, segment_object
from recon.capture.images import read_image, save_image
from recon.capture.normalization import box_corners, normalize
from recon.capture.scene import UNSURE_MASK_FOLDER, Frame, Scene, load_scene
from recon.capture.turntable import STILL_FOLDER
from recon.evaluation.views import load_view
from recon.geometry.visual_hull import hull_bounds
from recon.plots import mask_overview
from recon.runner.pipeline import StageContext

MASK_FOLDER = "masks"
OVERVIEW = 12
"""The masks' contact sheet (02_scene/masks.png) shows this many photos, spread over the capture."""
OVERVIEW_SIDE = 240
HULL_SEARCH = 0.25
"""A masked object's box may grow by up to this fraction of its size a side to hold the masks' visual hull."""
MIN_HULL_PHOTOS = 3
"""The masks' hull grows the box only when at least this many photos have background in their masks."""


def run(ctx: StageContext) -> dict:
    source = load_scene(ctx.inputs["poses"], ctx.source)
    scene = normalize(source, ctx.config)
    masked, why, in_hull = 0, "", None
    turntable = bool(source.notes.get("turntable"))
    if ctx.config.masks == "auto" and object_on_background(scene, turntable=turntable):
        masked, why, in_hull = _auto_masks(ctx, source, scene, turntable)
        if masked:
            scene = normalize(source, ctx.config)
    if scene.has_alpha and scene.capture == "object":
        scene = normalize(source, ctx.config, holds=_masks_hull(ctx, scene))
    if why:
        scene.notes["masks"] = why
    blurred = _leave_out_blurred(ctx, scene)
    scene.save(ctx.out)
    for key in ("up", "capture", "region", "masks", "box", "scale", "split"):
        if scene.notes.get(key):
            ctx.report.info(f"{key}: {scene.notes[key]}")
    counts = {s: len(scene.split(s)) for s in ("train", "val", "test")}
    near = min(f.near for f in scene.frames)
    far = max(f.far for f in scene.frames)
    return {
        "headline": f"{scene.capture} capture, {counts['train']}/{counts['val']}/{counts['test']} train/val/test views, "
        f"near {near:.3g} far {far:.3g}" + (f", {masked} automatic masks" if masked else "")
        + (f", {len(blurred)} blurred photo{'s' if len(blurred) > 1 else ''} left out" if blurred else ""),
        "capture": scene.capture,
        "split": counts,
        "aabb": scene.aabb.round(4).tolist(),
        "auto_masks": masked,
        "auto_masks_in_hull": in_hull,  # the median photo's share of its cut in the hull (None: no cut was made)
        "blurred": blurred,
    }


def _leave_out_blurred(ctx: StageContext, scene: Scene) -> dict[str, float]:
    """Drop the training photos far blurrier than those that share their view (`recon.capture.blur`), said with why;
    their sharpness shares, also kept in the scene's notes. A video's frames are not checked: choosing them already
    weighed a blurred stretch against a gap in the orbit (`recon.capture.video`)."""
    from recon.capture.blur import BLURRED_SHARE, blurred_photos
    from recon.capture.video import ANALYSIS_SIDE

    if ctx.config.blurred == "keep" or scene.source_kind == "video":
        return {}
    blurred = blurred_photos(scene, ANALYSIS_SIDE)
    if blurred:
        train = len(scene.split("train"))
        scene.frames = [f for f in scene.frames if f.name not in blurred]
        scene.notes["blurred"] = blurred
        ctx.report.warn(
            f"{len(blurred)} of {train} training photos are blurred (shaken or out of focus: "
            + ", ".join(f"{name} {share:.2f}" for name, share in blurred.items())
            + f" of the sharpness of the photos that share their view, under {BLURRED_SHARE}): left out of training "
            f"(normalize.blurred=keep keeps them)"
        )
    return blurred


def _auto_masks(ctx: StageContext, source: Scene, scene: Scene, turntable: bool = False) -> tuple[int, str, float]:
    """Cut the object out of every photo; when the cuts agree (or the capture is a turntable's, which nothing else
    can train), give `source`'s frames the masks (written to 02_scene/masks/). Returns how many photos got one (0:
    none), why, and the median photo's share of its cut inside the hull (what `MIN_AGREEMENT` judges)."""
    with ctx.report.task("automatic masks: cutting the object out of each photo", total=len(scene.frames)) as bar:
        found = segment_object(scene, progress=bar.advance, background=_still_background(ctx))
    in_hull = round(float(np.median(list(found.agreement.values()))), 4) if found.agreement else 0.0
    final = ctx.scene_dir / ctx.folder / MASK_FOLDER  # where the masks live once the stage folder is sealed
    home = "the video" if source.source_kind == "video" else "the photos folder"
    if not found.confident and turntable:
        ctx.report.warn(f"{found.reason}: used all the same, since on a turntable the room turns with the cameras and "
                        f"no field can hold it. Check {final}.png; to fix a mask, copy {final} next to {home} as "
                        f"masks/, edit it (white = object) and run again.")
    elif not found.confident:
        _write(ctx.out / UNSURE_MASK_FOLDER, found.masks, scene)  # a start for the user's masks; crops the mesh
        return 0, (
            f"{found.reason}: kept the photos unmasked, so the table and room are modelled too (contracted). "
            f"Give {home} a masks/ folder next to it (white = object; {final.with_name(UNSURE_MASK_FOLDER)} holds "
            f"these cuts, named as recon names the photos, to start from) to mesh the object alone"
        ), in_hull
    masks = {name: mask for name, mask in found.masks.items() if name not in found.astray}
    if found.astray:  # shows none of the object where SfM placed it: no part of the masked object's training
        source.frames = [f for f in source.frames if f.name in masks]
        ctx.report.warn(f"{len(found.astray)} photo(s) show none of the object where SfM placed them (an empty mask, "
                        f"and next to none of the object's sparse points seen): {', '.join(found.astray)}; left out "
                        "of training")
    with ctx.report.task("automatic masks: snapping each outline to the photo's edges", total=len(masks)) as bar:
        mattes = matte_photos(scene, masks, progress=bar.advance)
    _write(ctx.out / MASK_FOLDER, mattes, scene)
    for frame in source.frames:
        frame.mask_path = str(Path(ctx.folder) / MASK_FOLDER / f"{Path(frame.file_path).stem}.png")  # in the scene
    source.has_alpha = True
    return len(masks), (
        f"{found.reason}: trained and meshed as a masked object. To fix a mask, copy {final} next to {home} as "
        f"masks/, edit it (white = object) and run again"
    ), in_hull


def _still_background(ctx: StageContext) -> Callable[[Frame], np.ndarray | None] | None:
    """A turntable capture's still background, per photo (the poses stage's `recon.capture.turntable.STILL_FOLDER`);
    None for any other capture."""
    folder = Path(ctx.inputs["poses"]) / STILL_FOLDER
    if not folder.is_dir():
        return None

    def still(frame: Frame) -> np.ndarray | None:
        path = folder / f"{Path(frame.file_path).stem}.png"
        return read_image(path)[..., 0] > 0.5 if path.is_file() else None
    return still


def _masks_hull(ctx: StageContext, scene: Scene) -> np.ndarray | None:
    """The corners (8, 3), in the photos' (source) frame, of the box around the training photos' masks' visual hull,
    searched for in `scene`'s box grown by HULL_SEARCH a side and on the object's side of its ground or wall; None
    when the masks agree on nothing (the box stays as it is). Held-out photos score the result; they do not shape it."""
    box = np.asarray(scene.aabb, np.float64)
    search = box + np.stack([-(box[1] - box[0]), box[1] - box[0]]) * HULL_SEARCH
    written = Path(ctx.folder) / MASK_FOLDER  # this run's automatic masks are still in ctx.out
    objects, intrinsics, c2ws = [], [], []
    frames = scene.split("train") or scene.frames
    with ctx.report.task("fitting the box to the masks", total=len(frames)) as bar:
        for frame in frames:
            if frame.mask_path and Path(frame.mask_path).parent == written:
                frame = replace(frame, mask_path=str((ctx.out / MASK_FOLDER / Path(frame.mask_path).name).absolute()))
            view = load_view(scene, frame, SEGMENT_SIDE, keep_alpha=True)
            obj = view.image[..., 3] >= 128
            if not obj.all():  # a mask that calls the whole photo object says nothing of where the object ends
                objects.append(obj)
                intrinsics.append(view.intrinsics)
                c2ws.append(frame.c2w)
            bar.advance()
    if len(objects) < MIN_HULL_PHOTOS:
        return None
    support = None
    if scene.ground is not None:  # the ground or wall the object stands on, its normal turned towards the object
        support = np.asarray(scene.ground, np.float64)
        middle = box.mean(axis=0) if scene.region is None else np.asarray(scene.region, np.float64).mean(axis=0)
        support = support if support[:3] @ middle >= support[3] else -support
    bounds = hull_bounds(search, HULL_RES, c2ws, intrinsics, objects, support=support)
    if bounds is None:
        return None
    corners = np.concatenate([box_corners(bounds), np.ones((8, 1))], axis=1)
    return (corners @ np.asarray(scene.source_from_world, np.float64).T)[:, :3]


def _write(folder: Path, masks: dict[str, np.ndarray], scene: Scene) -> None:
    """Each mask (bool, or uint8 0-255) as a PNG (white = object) named like its photo, and a contact sheet of up to
    OVERVIEW photos beside the folder (`<folder>.png`) with their background dimmed."""

    def as_float(mask: np.ndarray) -> np.ndarray:  # bool cuts, or uint8 mattes (`matte_photos`)
        return mask.astype(np.float32) / 255.0 if mask.dtype == np.uint8 else mask.astype(np.float32)

    folder.mkdir(parents=True, exist_ok=True)
    for name, mask in masks.items():
        save_image(folder / f"{Path(name).stem}.png", as_float(mask)[..., None])
    frames = [f for f in scene.frames if f.name in masks]
    shown = [frames[i] for i in np.linspace(0, len(frames) - 1, min(OVERVIEW, len(frames))).round().astype(int)]
    photos = [read_image(scene.image_path(f), max_side=OVERVIEW_SIDE) for f in shown]
    mask_overview(photos, [as_float(masks[f.name]) for f in shown], folder.with_suffix(".png"))

