"""Turntable captures: a camera standing still while the object turns in front of it.

Structure from motion needs the scene to hold still while the camera moves. On a turntable the object turns and the
room stays put, so every photo of one camera position shows the room at the same pixels: SfM matches the room, finds
that the camera never moved, and poses every photo in one place. What the photos of one camera position share pixel
for pixel is that still background; what changes between them is the turning object. Features are then taken only
where the photos change, and SfM recovers the cameras as they move around the object in the object's own frame.

Pure numpy/OpenCV on the photos COLMAP reads; the poses stage decides what to do with the answer.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

SIDE = 320
"""Photos are compared at this longest side (pixels)."""
LOG_FLOOR = 0.02
"""Added to the gray level (0-1) before its logarithm, so that the noise of dark pixels does not dominate."""
AGREE = 0.08
"""Two photos show the same thing at a pixel where their log gray levels differ by less than this (about 8%), once
their exposures are matched."""
TEXTURE = 0.03
"""A pixel counts as textured where its log gray level changes by more than this to the next pixel: only there can
a moved camera be told from a still one (a plain wall agrees with itself wherever the camera stands)."""
CELLS = 8
"""Photos are compared in a grid of this many cells a side: a still camera's photos agree all over the cells that
show only the room, a moved camera's nowhere entirely, however close it stayed."""
CELL_TEXTURED = 0.1
"""A cell counts where at least this share of its pixels is textured."""
CELL_AGREE = 0.9
"""A cell shows the same thing in two photos where over this share of its textured pixels agree."""
STILL_SHARE = 0.2
"""Two photos are from one camera position when over this share of their counted cells show the same thing: the
object (and the platter turning with it) may fill most of the frame, as long as some of the room shows."""
NEIGHBOURS = 3
"""Each photo is compared with this many photos after it in name order (the order they were taken in)."""
MIN_GROUP = 6
"""A camera position counts when at least this many photos were taken from it: a turn in fewer stops leaves SfM too
little overlap between them, and exposure brackets (several shots from one place, 3, 5 or 7) are no turntable."""
MIN_SHARE = 0.5
"""A capture is a turntable capture when photos from such positions are at least this share of it."""
MIN_MOVING = 0.02
"""... and what changes between the photos of a position is at least this share of a photo: several photos of a
still scene from one place are copies, not a turntable."""
GROW = 0.02
"""The changing region is grown by this fraction of the photo's longest side: the object's outline and what its
features' windows reach beyond it."""

ROOM_SHARE = 0.5
"""A pixel shows a position's still background in the median of its photos where at least this share of them agree
there (the object turns through it in the others); where the object always stands, they agree only by chance."""
STILL_PIECE = 0.002
"""A piece of still background counts when it covers at least this share of the photo."""
STILL_FOLDER = "still"
"""Where the poses stage writes each turntable photo's `Turntable.background` (white), named like the photo (PNG):
normalize's automatic masks take it as background."""


@dataclass
class Turntable:
    """The answer for a capture that is a turntable capture."""

    groups: list[list[int]]
    """The photos (indices) taken from each still camera position."""
    moving: dict[int, np.ndarray]
    """Per photo of a group, where it differs from its position's still background: (h, w) bool at the compared
    size (`SIDE`)."""
    background: dict[int, np.ndarray]
    """Per photo of a group, where it shows its position's still background ((h, w) bool at `SIDE`): it agrees with
    the median where most photos do (`ROOM_SHARE`), over 3×3 pixels (a speck of the object may match by chance),
    at textured pixels (a plain part of the object that stays in place as it turns agrees as well).
    It is what tells the object's holes (the table seen through them) from the object: no sparse point lies there."""
    photos: int
    """How many photos the capture has."""

    def moving_share(self, i: int) -> float:
        return float(self.moving[i].mean())

    def reason(self) -> str:
        held = sum(len(g) for g in self.groups)
        share = np.median([self.moving_share(i) for i in self.moving])
        positions = f"{len(self.groups)} camera position" + ("s" if len(self.groups) > 1 else "")
        return (f"turntable: {held} of {self.photos} photos show the same background pixel for pixel from "
                f"{positions}, the object changing in front of it ({share:.0%} of a photo on the median): a camera "
                f"standing still while the object turns. Features are taken only where the photos change, so "
                f"structure from motion places the cameras around the object instead of all in one place.")


def _log_gray(image: np.ndarray) -> np.ndarray:
    """(h, w) float32 log gray level at `SIDE`, lightly blurred (noise, JPEG blocks)."""
    import cv2

    img = np.asarray(image, np.float32)  # in [0, 1], as `recon.capture.images.read_image` reads photos
    gray = img[..., :3].mean(axis=2) if img.ndim == 3 else img
    h, w = gray.shape
    scale = SIDE / max(h, w)
    if scale < 1.0:
        gray = cv2.resize(gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(np.log(gray + LOG_FLOOR), (0, 0), 1.0)


def _textured(log_gray: np.ndarray) -> np.ndarray:
    dx = np.abs(np.diff(log_gray, axis=1, append=log_gray[:, -1:]))
    dy = np.abs(np.diff(log_gray, axis=0, append=log_gray[-1:, :]))
    return np.maximum(dx, dy) > TEXTURE


def agreement(a: np.ndarray, b: np.ndarray) -> float:
    """The share of a's textured cells (`CELLS`) in which b shows the same (log gray images of one size),
    exposures matched by the median difference."""
    textured = _textured(a)
    if textured.sum() < 0.01 * textured.size:
        return 0.0  # a plain photo says nothing about whether the camera moved
    d = a - b
    agree = (np.abs(d - np.median(d[textured])) < AGREE) & textured
    h, w = a.shape
    rows, cols = np.arange(h) * CELLS // h, np.arange(w) * CELLS // w
    cell = (rows[:, None] * CELLS + cols[None, :]).ravel()
    pixels = np.bincount(cell, minlength=CELLS * CELLS)
    tex = np.bincount(cell, textured.ravel(), minlength=CELLS * CELLS)
    same = np.bincount(cell, agree.ravel(), minlength=CELLS * CELLS)
    counted = tex >= CELL_TEXTURED * pixels
    if not counted.any():
        return 0.0
    return float(np.mean(same[counted] > CELL_AGREE * tex[counted]))


def _groups(logs: Sequence[np.ndarray]) -> list[list[int]]:
    """Connected photos of one camera position (each compared with its `NEIGHBOURS` successors)."""
    parent = list(range(len(logs)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(len(logs)):
        for j in range(i + 1, min(len(logs), i + 1 + NEIGHBOURS)):
            if logs[i].shape != logs[j].shape:
                continue  # photos of two sizes: two cameras, or one turned
            if min(agreement(logs[i], logs[j]), agreement(logs[j], logs[i])) > STILL_SHARE:
                parent[root(j)] = root(i)
    members: dict[int, list[int]] = {}
    for i in range(len(logs)):
        members.setdefault(root(i), []).append(i)
    return [m for m in members.values() if len(m) >= MIN_GROUP]


def _moving(logs: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per photo of one position, where it differs from the position's still background (the per-pixel median of
    its photos, their exposures matched), cleaned of specks and holes and grown by `GROW`; and where it shows that
    background (`Turntable.background`)."""
    import cv2

    stack = np.stack(logs)
    median = np.median(stack, axis=0)
    gains = np.median((stack - median).reshape(len(logs), -1), axis=1)
    median = np.median(stack - gains[:, None, None], axis=0)
    h, w = median.shape
    grow = max(1, round(GROW * max(h, w)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    small = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    agrees = np.abs(stack - gains[:, None, None] - median) < AGREE
    room = agrees.mean(axis=0) >= ROOM_SHARE  # where the median is the room's, not the object's
    out, still = [], []
    window = np.ones((3, 3), np.uint8)
    for agree, log in zip(agrees, stack):
        # only where textured: a plain part of the object that stays in place as it turns (a vase's body) agrees too
        sure = cv2.erode((agree & room).astype(np.uint8), window) & _textured(log).astype(np.uint8)
        # and in the room's large pieces, not in specks where the object's own texture blurs into a plain part of it
        count, labels, stats, _ = cv2.connectedComponentsWithStats(sure, connectivity=8)
        large = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= STILL_PIECE * sure.size)
        still.append(np.isin(labels, large[large > 0]))
        changed = (~agree).astype(np.uint8)
        changed = cv2.morphologyEx(changed, cv2.MORPH_OPEN, small)  # noise: single pixels
        changed = cv2.morphologyEx(changed, cv2.MORPH_CLOSE, disc)  # the object's parts that match the room by chance
        out.append(cv2.dilate(changed, disc).astype(bool))
    return out, still


def find_turntable(images: Sequence[np.ndarray]) -> Turntable | None:
    """A `Turntable` when most of these photos (in the order taken) come in groups from still camera positions with
    something changing in front of the camera; None for a camera that moved (or copies of one still scene)."""
    return turntable_verdict(images)[0]


def turntable_verdict(images: Sequence[np.ndarray]) -> tuple[Turntable | None, str]:
    """`find_turntable`'s answer with the reason the poses stage prints either way."""
    logs = [_log_gray(img) for img in images]
    groups, moving, background, copies = [], {}, {}, 0
    for group in _groups(logs):
        masks, still = _moving([logs[i] for i in group])
        if np.median([m.mean() for m in masks]) < MIN_MOVING:
            copies += len(group)  # nothing turned: copies
            continue
        groups.append(group)
        moving.update(zip(group, masks))
        background.update(zip(group, still))
    held = sum(len(g) for g in groups)
    if held < MIN_SHARE * len(images) or not groups:
        if held + copies == 0:
            why = f"no {MIN_GROUP} or more photos share one still camera position: the camera moved between shots"
        else:
            still = f", {copies} more show one still scene without change (copies)" if copies else ""
            why = (f"{held} of {len(images)} photos come from still camera positions with something turning in "
                   f"front of them{still}; a turntable capture has {MIN_SHARE:.0%} or more")
        return None, f"turntable: no ({why}; poses.turntable=off skips this check)"
    found = Turntable(groups=groups, moving=moving, background=background, photos=len(images))
    return found, found.reason()


def feature_mask(turntable: Turntable, i: int, size: tuple[int, int]) -> np.ndarray:
    """Where features of photo i are taken, (height, width) bool for a photo of (width, height): where it changes.
    A photo of no group (taken by hand between the turns) keeps every pixel."""
    import cv2

    if i not in turntable.moving:
        return np.ones((size[1], size[0]), bool)
    return cv2.resize(turntable.moving[i].astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
