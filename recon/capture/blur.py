"""Photos shaken or out of focus: each photo's sharpness against the photos that share most of its view.

A hand-held photo taken in a jerk, or focused behind the object, trains its blur into the field: the colour loss
pulls every surface it sees towards a smear the other photos contradict, and the mesh's colours are baked from it
too. Sharpness alone cannot tell such a photo (a close-up of a plain part has few edges when sharp), so each photo is
compared with the `NEIGHBOURS` photos that see most of the same sparse points: the same part of the object, at about
the same scale. The measure is the variance of the Laplacian over the variance of the gray levels, at
`recon.capture.video.ANALYSIS_SIDE`: blur removes the high frequencies the first sums, while a darker or brighter
exposure scales both alike.
"""
from __future__ import annotations

import numpy as np

from recon.capture.images import read_image
from recon.capture.scene import Frame, Scene

BLURRED_SHARE = 0.35
"""A training photo whose sharpness is under this share of its neighbours' median is blurred: below every sharp photo
of a real capture and above most photos shaken along 0.5% of their width (benchmarks/results/blur_shares_fox.json;
what leaving them out gains: benchmarks/results/blurred_photos.json)."""
NEIGHBOURS = 4
CLOSER = 1.25
"""A photo whose view spans this many times less than its neighbours' (a close-up among wider views) is not judged:
magnified, the object's own texture is smoother than the table and room the wider views hold."""
MIN_TRAINING_PHOTOS = 20
"""With fewer training photos every photo is kept: each view counts more than its blur costs."""
MOST_LEFT_OUT = 1 / 8
"""At most this share of the training photos is left out (the blurriest first): a capture blurred throughout
trains on what it has."""


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian over the variance of the gray levels (independent of the exposure's gain)."""
    import cv2

    gray = np.asarray(gray, np.float32)
    spread = float(gray.var())
    return float(cv2.Laplacian(gray, cv2.CV_32F).var()) / spread if spread > 0 else 0.0


def sharpness_shares(scene: Scene, side: int) -> dict[str, float]:
    """{frame name: its sharpness over the median of its `NEIGHBOURS`'}, for the frames with sparse points (SfM's),
    close-ups among wider views left out (`CLOSER`)."""
    names = [f.name for f in scene.frames if len(scene.point_visibility.get(f.name, ())) > 0]
    if len(names) <= NEIGHBOURS:
        return {}
    from scipy.sparse import csr_matrix

    by_name = {f.name: f for f in scene.frames}
    sharp = np.array([sharpness(read_image(scene.image_path(by_name[n]), max_side=side)[..., :3].mean(axis=-1))
                      for n in names])
    seen = [np.unique(np.asarray(scene.point_visibility[n], np.int64)) for n in names]
    rows = np.repeat(np.arange(len(names)), [len(s) for s in seen])
    views = csr_matrix((np.ones(len(rows)), (rows, np.concatenate(seen))))
    shared = (views @ views.T).toarray()  # points each two photos both see
    np.fill_diagonal(shared, -1)
    nearest = np.argsort(-shared, axis=1, kind="stable")[:, :NEIGHBOURS]
    span = _view_span(scene, [by_name[n] for n in names])
    return {name: float(sharp[i] / max(np.median(sharp[nearest[i]]), 1e-12)) for i, name in enumerate(names)
            if span is None or span[i] * CLOSER >= np.median(span[nearest[i]])}


def _view_span(scene: Scene, frames: list[Frame]) -> np.ndarray | None:
    """How wide each photo's view is at the box's centre (its distance over its focal length in widths): a close-up
    spans less. None without a box."""
    if scene.aabb is None:
        return None
    center = np.asarray(scene.aabb, np.float64).mean(axis=0)
    return np.array([np.linalg.norm(f.c2w[:3, 3] - center) * f.w / f.fl_x for f in frames])


def blurred_photos(scene: Scene, side: int) -> dict[str, float]:
    """{training frame name: its sharpness share} of the training photos to leave out, the blurriest first; empty
    with under `MIN_TRAINING_PHOTOS` training photos."""
    train = scene.split("train")
    if len(train) < MIN_TRAINING_PHOTOS:
        return {}
    shares = sharpness_shares(scene, side)
    blurred = sorted((shares[f.name], f.name) for f in train if shares.get(f.name, 1.0) < BLURRED_SHARE)
    most = min(int(len(train) * MOST_LEFT_OUT), len(train) - MIN_TRAINING_PHOTOS)
    return {name: round(share, 3) for share, name in blurred[:max(most, 0)]}
