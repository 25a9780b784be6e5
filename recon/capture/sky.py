"""Which pixels of a photo are sky: smooth, blue (or pale beside the blue), reached from the top edge, no SfM point near.

A field with a plain background colour cannot show a blue sky that brightens towards the horizon, so it
paints the sky into its density as blobs just above the roofs (sceaux_castle), and those blobs are mesh.
The train stage gives such scenes a sky colour per ray direction and trains the pixels found here as empty
space (`recon.plans.training.sky_for`). The test is conservative: a pixel is sky only when it is

- smooth (colour gradient below `SKY_MAX_GRADIENT` per pixel after a 1-pixel blur; clouds' edges and every
  textured surface fail),
- blue (blue channel above red by `SKY_MIN_BLUE_EXCESS` and not below green; a white wall or an overcast sky
  with no blue above it is left to the field: it cannot be told from a surface by colour),
- far from every sparse point the photo observes (`SKY_POINT_MARGIN` of the photo's width): features are
  found on surfaces, never on a clear sky, so a blue, smooth wall with SfM points on it is not sky,
- and connected to the photo's top edge through such pixels, in a region of at least `SKY_MIN_REGION` of the photo
  (a few smooth blue pixels of a texture touching the top edge are not a sky);
- or smooth, far from the points, bright and not redder than blue (`SKY_HAZE_MIN_BRIGHTNESS`), and connected to
  that blue sky: the pale haze towards the horizon and the glare around the sun (on sceaux_castle up to 28% of a
  photo beyond the blue; left out, the field painted it into its density).
A pixel left out trains as it always did, so a miss costs nothing but the blobs it could have removed.
"""
from __future__ import annotations

import cv2
import numpy as np

SKY_MAX_GRADIENT = 0.02
"""Largest colour change per pixel (Sobel, RGB norm, in [0, 1] units) in the sky: a clear sky's gradient at 400 px
is ~0.002 per pixel; the castle's roof slates and walls are 0.05-0.3."""
SKY_MIN_BLUE_EXCESS = 0.05
"""Blue must exceed red by this much (a clear sky: 0.2-0.4 on the castle's photos; the fox's cream wallpaper: below 0)."""
SKY_POINT_MARGIN = 0.02
"""Pixels within this fraction of the photo's width of an observed sparse point are not sky (the roof line's
points keep the sky test ~8 px away from it at 400 px)."""
SKY_MIN_REGION = 0.005
"""Smallest connected sky region, as a fraction of the photo's pixels."""
SKY_HAZE_MIN_BRIGHTNESS = 0.6
"""Pale sky grown from the blue sky: every channel above this (the castle's haze: 0.75-1)."""
SKY_MIN_FRACTION = 0.01
"""auto models a sky when at least this fraction of the training pixels are sky."""


def sky_mask(image: np.ndarray, points_uv: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of an RGB photo (H, W, 3+) uint8 that are sky (module docstring).

    points_uv: (P, 2) pixel positions (x right, y down) of the sparse points the photo observes."""
    img = image[..., :3].astype(np.float32) / 255.0
    h, w = img.shape[:2]
    blur = cv2.GaussianBlur(img, (0, 0), 1.0)
    gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)
    gradient = np.sqrt((gx * gx + gy * gy).sum(-1)) / 8.0  # the 3x3 Sobel sums 8 pixel differences
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    open_sky = gradient < SKY_MAX_GRADIENT
    uv = np.asarray(points_uv, np.float64).reshape(-1, 2)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if inside.any():
        marks = np.zeros((h, w), np.uint8)
        marks[uv[inside, 1].astype(int), uv[inside, 0].astype(int)] = 1
        r_px = max(1, round(SKY_POINT_MARGIN * w))
        near = cv2.dilate(marks, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r_px + 1, 2 * r_px + 1)))
        open_sky &= near == 0
    blue = open_sky & (b > r + SKY_MIN_BLUE_EXCESS) & (b >= g - 0.02)
    count, labels = cv2.connectedComponents(blue.astype(np.uint8), connectivity=4)
    sizes = np.bincount(labels.reshape(-1), minlength=count)
    top = [i for i in np.unique(labels[0][labels[0] > 0]) if sizes[i] >= SKY_MIN_REGION * h * w]
    seeds = np.isin(labels, top)
    if not seeds.any():
        return seeds
    haze = open_sky & (img.min(-1) > SKY_HAZE_MIN_BRIGHTNESS) & (b >= r - 0.02)
    _, grown = cv2.connectedComponents((blue | haze).astype(np.uint8), connectivity=4)
    return np.isin(grown, np.unique(grown[seeds]))
