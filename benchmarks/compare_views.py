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

    from recon.capture.scene import load_scene
    from recon.evaluation.views import load_view, render_view, target_rgb
    from recon.field import load_field

    fields, labels = args.fields.split(","), args.labels.split(",")
    if len(fields) != len(labels):
        print(f"error: {len(fields)} fields but {len(labels)} labels: give one label per field", file=sys.stderr)
        return 2
    scene = load_scene(args.scene / "02_scene")
    frames = {Path(f.file_path).stem: f for f in scene.split("test")}
    missing = [v for v in args.views.split(",") if v not in frames]
    if missing:
        print(f"error: {args.scene} has no test photo named {', '.join(missing)}", file=sys.stderr)
        return 2
    models = [load_field(Path(f)) for f in fields]
    rows = []
    for name in args.views.split(","):
        cells: list[np.ndarray] = []
        texts: list[str] = []
        for (model, meta), label in zip(models, labels, strict=True):
            view = load_view(scene, frames[name], int(meta.get("max_side") or 400), keep_alpha=True)
            background = np.asarray(meta["background"], np.float32)
            aabb = torch.tensor(meta["aabb"], dtype=torch.float32) if meta.get("bounded") else None
            photo = target_rgb(view, background)
            if not cells:
                cells.append(photo)
                texts.append(f"{name}: photo")
            with torch.no_grad():
                rgb = render_view(model, view, aabb, background)["rgb"].astype(np.float32)
            psnr = -10 * np.log10(max(float(np.mean((rgb - photo) ** 2)), 1e-12))
            cells.append(rgb)
            texts.append(f"{label}: {psnr:.2f} dB")
        row = Image.fromarray((np.clip(np.concatenate(cells, 1), 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(row)
        for k, text in enumerate(texts):
            draw.text((k * cells[0].shape[1] + 6, 6), text, fill=(0, 0, 0))
        rows.append(np.asarray(row))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".tmp.png")
    Image.fromarray(np.concatenate(rows, 0)).save(tmp)
    tmp.replace(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
