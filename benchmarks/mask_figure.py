"""Photos beside their true masks and the masks recon made for them: a PNG, a row per photo.

    python benchmarks/mask_figure.py --masks SCENE/02_scene/masks --photos DATA/photos --truth DATA/capture/masks \
        --views view_000,view_004,view_016 --out docs/wall_mounted_board.png

MASKS is a scene's automatic masks (the normalize stage's `02_scene/masks`, or `masks_unsure` when they were not
trusted), named like the photos; TRUTH the generator's true masks (gen_tabletop.py's `capture/masks`). Each row: the
photo, the true mask, recon's mask, and recon's IoU against the truth printed on it. `--masks LABEL=MASKS` again adds
another set of masks beside (e.g. before and after a change); `--crop F` shows only the true mask's box grown by F of
its size on each side.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figures import side_by_side, write_png  # noqa: E402

TILE_WIDTH = 320


def _read(path: Path, size: tuple[int, int] | None = None) -> Image.Image:
    image = Image.open(path)
    return image.resize(size, Image.BILINEAR) if size is not None else image


def _find(folder: Path, stem: str) -> Path:
    found = sorted(folder.glob(f"{stem}.*"))
    if not found:
        raise SystemExit(f"no image named {stem}.* in {folder}")
    return found[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--masks", action="append", required=True, help="recon's masks folder, or LABEL=folder (repeatable)")
    parser.add_argument("--photos", type=Path, required=True)
    parser.add_argument("--truth", type=Path, required=True, help="the true masks folder")
    parser.add_argument("--views", required=True, help="comma-separated photo stems, e.g. view_000,view_004")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--crop", type=float, default=None, help="crop to the true mask's box grown by this fraction")
    a = parser.parse_args()
    sets = [(m.split("=", 1)[0], Path(m.split("=", 1)[1])) if "=" in m else ("", Path(m)) for m in a.masks]

    rows = []
    for stem in a.views.split(","):
        photo = _read(_find(a.photos, stem)).convert("RGB")
        size = photo.size
        truth = np.asarray(_read(_find(a.truth, stem), size).convert("L")) > 127
        tiles, labels = [photo, Image.fromarray(truth.astype(np.uint8) * 255).convert("RGB")], []
        for label, folder in sets:
            mask = np.asarray(_read(_find(folder, stem), size).convert("L")) > 127
            iou = float((mask & truth).sum() / max((mask | truth).sum(), 1))
            tiles.append(Image.fromarray(mask.astype(np.uint8) * 255).convert("RGB"))
            labels.append(f"{label + ': ' if label else ''}{stem}: IoU {iou:.3f}")
        if a.crop is not None:
            ys, xs = np.nonzero(truth)
            grow_x, grow_y = a.crop * (xs.max() - xs.min()), a.crop * (ys.max() - ys.min())
            box = (max(0, int(xs.min() - grow_x)), max(0, int(ys.min() - grow_y)),
                   min(size[0], int(xs.max() + grow_x) + 1), min(size[1], int(ys.max() + grow_y) + 1))
            tiles = [t.crop(box) for t in tiles]
        height = round(TILE_WIDTH * tiles[0].height / tiles[0].width)
        row = side_by_side([t.resize((TILE_WIDTH, height), Image.BILINEAR) for t in tiles])
        draw = ImageDraw.Draw(row)
        for k, text in enumerate(labels):
            draw.text(((2 + k) * TILE_WIDTH + 6, 6), text, fill=(255, 64, 64))
        rows.append(row)
    figure = Image.new("RGB", (rows[0].width, sum(r.height for r in rows)))
    y = 0
    for row in rows:
        figure.paste(row, (0, y))
        y += row.height
    write_png(figure, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
