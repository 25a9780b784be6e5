"""Test views of one scene rendered by several trained fields, beside the photo, with each render's PSNR: a PNG.

    python benchmarks/compare_views.py --scene SCENE --fields A/03_field,B/03_field --labels "one level,two levels" \
        --views r_40,r_16 --out docs/gpu_feature_levels.png

SCENE is the scene folder whose test photos and cameras are used (its 02_scene); each field is a trained
03_field folder of that scene (e.g. two rows of an option sweep, the first copied aside before the second replaces
it). Renders one ray a pixel at the field's training size; a row per view, a column per field.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's recon, not an installed one


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--fields", required=True, help="comma-separated 03_field folders")
    parser.add_argument("--labels", required=True, help="comma-separated, one per field")
    parser.add_argument("--views", required=True, help="comma-separated test photo names, e.g. r_40,r_16")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()

    from recon.atomic import atomic_open
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.evaluation.metrics import psnr
    from recon.evaluation.views import load_view, render_view, target_rgb
    from recon.field import load_field

    fields, labels = args.fields.split(","), args.labels.split(",")
    if len(fields) != len(labels):
        print(f"error: {len(fields)} fields but {len(labels)} labels: give one label per field", file=sys.stderr)
        return 2
    scene = load_scene(args.scene / "02_scene", recorded_source(args.scene))
    frames = {Path(f.file_path).stem: f for f in scene.split("test")}
    missing = [v for v in args.views.split(",") if v not in frames]
    if missing:
        print(f"error: {args.scene} has no test photo named {', '.join(missing)}", file=sys.stderr)
        return 2
    models = [load_field(Path(f)) for f in fields]
    rows = []
    # one scene, so one training size and background: the first field's
    max_side, background = int(models[0][1].get("max_side") or 400), np.asarray(models[0][1]["background"], np.float32)
    for name in args.views.split(","):
        view = load_view(scene, frames[name], max_side, keep_alpha=True)
        photo = target_rgb(view, background)
        cells, texts = [photo], [f"{name}: photo"]
        for (model, meta), label in zip(models, labels, strict=True):
            aabb = torch.tensor(meta["aabb"], dtype=torch.float32) if meta.get("bounded") else None
            with torch.no_grad():
                rgb = render_view(model, view, aabb, background)["rgb"].astype(np.float32)
            cells.append(rgb)
            texts.append(f"{label}: {float(psnr(torch.from_numpy(rgb), torch.from_numpy(photo))):.2f} dB")
        row = Image.fromarray((np.clip(np.concatenate(cells, 1), 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(row)
        for k, text in enumerate(texts):
            draw.text((k * cells[0].shape[1] + 6, 6), text, fill=(0, 0, 0))
        rows.append(np.asarray(row))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out) as f:
        Image.fromarray(np.concatenate(rows, 0)).save(f, format="PNG")
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
