"""docs/turntable.png from the turntable records' scenes: one photo, where SfM takes its features, the still room it
shows, its automatic mask, the mesh, and the mesh of the run with features from every pixel.

    RECORD_NAME=tabletop_turntable_fast BENCH_WORK=/tmp/tt benchmarks/record.sh tabletop_turntable fast
    RECORD_NAME=tabletop_turntable_fast_off BENCH_WORK=/tmp/tt_off benchmarks/record.sh tabletop_turntable fast \\
        --set poses.turntable=off
    python benchmarks/turntable_figure.py --scene /tmp/tt/tabletop_turntable-fast \\
        --off /tmp/tt_off/tabletop_turntable-fast --out docs/turntable.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

PANEL = (320, 240)
"""Each panel's (width, height)."""
DIM = 0.3
"""Brightness left where a panel's mask is off."""
STILL_BLUE = np.array([40, 40, 255], np.uint8)
"""The still room's colour (RGB) over the photo."""


def _read(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SystemExit(f"{path}: missing or not an image; run the records' commands first (see this file's top)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img


def _fit(img: np.ndarray, interpolation: int = cv2.INTER_AREA) -> np.ndarray:
    """img resized to PANEL (a mesh preview: letterboxed on white, its aspect kept)."""
    w, h = PANEL
    if img.shape[1] * h == img.shape[0] * w:
        return cv2.resize(img, PANEL, interpolation=interpolation)
    scale = min(w / img.shape[1], h / img.shape[0])
    small = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)), interpolation=interpolation)
    out = np.full((h, w, 3), 255, np.uint8)
    y, x = (h - small.shape[0]) // 2, (w - small.shape[1]) // 2
    out[y:y + small.shape[0], x:x + small.shape[1]] = small
    return out


def _dim_outside(photo: np.ndarray, mask: np.ndarray) -> np.ndarray:
    keep = _fit(mask, cv2.INTER_NEAREST) > 127
    return np.where(keep[..., None], photo, (photo * DIM).astype(np.uint8))


def figure(scene: Path, off: Path, photos: Path, name: str) -> np.ndarray:
    """The six panels (2 rows of 3) as one RGB image."""
    photo = _fit(_read(photos / name))
    stem = Path(name).stem
    features = _read(scene / "01_poses" / "colmap" / "feature_masks" / f"{name}.png", cv2.IMREAD_GRAYSCALE)
    still = _fit(_read(scene / "01_poses" / "still" / f"{stem}.png", cv2.IMREAD_GRAYSCALE), cv2.INTER_NEAREST) > 127
    mask = _read(scene / "02_scene" / "masks" / f"{stem}.png", cv2.IMREAD_GRAYSCALE)
    panels = [photo, _dim_outside(photo, features), np.where(still[..., None], STILL_BLUE, photo),
              _dim_outside(photo, mask), _fit(_read(scene / "04_mesh" / "preview_front.png")),
              _fit(_read(off / "04_mesh" / "preview_front.png"))]
    return np.vstack([np.hstack(panels[:3]), np.hstack(panels[3:])])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, required=True, help="the recognised run's scene folder")
    ap.add_argument("--off", type=Path, required=True, help="the run with poses.turntable=off")
    ap.add_argument("--photos", type=Path, default=Path.home() / ".cache/recon/datasets/tabletop_turntable/photos")
    ap.add_argument("--photo", default="view_003.jpg")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    img = figure(a.scene, a.off, a.photos, a.photo)
    tmp = a.out.with_name(f".{a.out.stem}.tmp.png")
    cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    tmp.replace(a.out)
    print(f"figure: {a.out}")


if __name__ == "__main__":
    main()
