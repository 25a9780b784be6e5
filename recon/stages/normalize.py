"""normalize stage: the canonical scene (upright, centred, scaled), near/far per camera, the data split."""
from __future__ import annotations

from recon.normalization import normalize
from recon.pipeline import Stage, StageContext
from recon.scene import load_scene


def run(ctx: StageContext) -> dict:
    source = load_scene(ctx.inputs["poses"])
    scene = normalize(source, ctx.config)
    scene.save(ctx.out)
    for key in ("up", "capture", "region", "box", "scale", "split"):
        if scene.notes.get(key):
            ctx.report.info(f"{key}: {scene.notes[key]}")
    counts = {s: len(scene.split(s)) for s in ("train", "val", "test")}
    near = min(f.near for f in scene.frames)
    far = max(f.far for f in scene.frames)
    return {
        "headline": f"{scene.capture} capture, {counts['train']}/{counts['val']}/{counts['test']} train/val/test views, "
        f"near {near:.3g} far {far:.3g}",
        "capture": scene.capture,
        "split": counts,
        "aabb": scene.aabb.round(4).tolist(),
    }


# version 3: the box holds the linked sparse points (stray ones dropped) instead of the 2 %–98 % percentiles, so a
# thin part is no longer cut off; its margin went from 10 % to 5 % of the size on each side
# version 4: with no ground under the object, a wall behind it (every camera in front) is found and cut like the ground
STAGE = Stage(name="normalize", folder="02_scene", inputs=("poses",), version=4, run=run)
