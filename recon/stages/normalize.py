"""normalize stage: the canonical scene (upright, centred, scaled), near/far per camera, the data split, and — for an
object photographed without masks in front of its table and room — the object's masks cut from the photos."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.capture.auto_masks import matte_photos, object_on_background, segment_object
from recon.capture.images import read_image, save_image
from recon.capture.normalization import normalize
from recon.capture.scene import Scene, load_scene
from recon.plots import mask_overview
from recon.runner.pipeline import Stage, StageContext

MASK_FOLDER = "masks"
OVERVIEW = 12
"""The masks' contact sheet (02_scene/masks.png) shows this many photos, spread over the capture."""
OVERVIEW_SIDE = 240


def run(ctx: StageContext) -> dict:
    source = load_scene(ctx.inputs["poses"])
    scene = normalize(source, ctx.config)
    masked, why = 0, ""
    if ctx.config.masks == "auto" and object_on_background(scene):
        masked, why = _auto_masks(ctx, source, scene)
        if masked:
            scene = normalize(source, ctx.config)
        scene.notes["masks"] = why
    scene.save(ctx.out)
    for key in ("up", "capture", "region", "masks", "box", "scale", "split"):
        if scene.notes.get(key):
            ctx.report.info(f"{key}: {scene.notes[key]}")
    counts = {s: len(scene.split(s)) for s in ("train", "val", "test")}
    near = min(f.near for f in scene.frames)
    far = max(f.far for f in scene.frames)
    return {
        "headline": f"{scene.capture} capture, {counts['train']}/{counts['val']}/{counts['test']} train/val/test views, "
        f"near {near:.3g} far {far:.3g}" + (f", {masked} automatic masks" if masked else ""),
        "capture": scene.capture,
        "split": counts,
        "aabb": scene.aabb.round(4).tolist(),
        "auto_masks": masked,
    }


def _auto_masks(ctx: StageContext, source: Scene, scene: Scene) -> tuple[int, str]:
    """Cut the object out of every photo; when the cuts agree, give `source`'s frames the masks (written to
    02_scene/masks/). Returns how many photos got one (0: none) and why."""
    with ctx.report.task("automatic masks: cutting the object out of each photo", total=len(scene.frames)) as bar:
        found = segment_object(scene, progress=bar.advance)
    final = ctx.scene_dir / ctx.folder / MASK_FOLDER  # where the masks live once the stage folder is sealed
    if not found.confident:
        _write(ctx.out / "masks_unsure", found.masks, scene)  # for a look; not used
        return 0, (
            f"{found.reason}: kept the photos unmasked, so the table and room are modelled too (contracted). "
            f"Give the photos a masks/ folder (white = object) to mesh the object alone"
        )
    with ctx.report.task("automatic masks: snapping each outline to the photo's edges", total=len(found.masks)) as bar:
        mattes = matte_photos(scene, found.masks, progress=bar.advance)
    _write(ctx.out / MASK_FOLDER, mattes, scene)
    for frame in source.frames:
        frame.mask_path = str(final / f"{Path(frame.file_path).stem}.png")
    source.has_alpha = True
    return len(found.masks), (
        f"{found.reason}: trained and meshed as a masked object. To fix a mask, copy {final} next to the photos "
        f"folder as masks/, edit it (white = object) and run again"
    )


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


# version 6: automatic masks are soft at their outlines, snapped to the photos' edges
STAGE = Stage(name="normalize", folder="02_scene", inputs=("poses",), version=6, run=run)
