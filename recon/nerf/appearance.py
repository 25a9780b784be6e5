"""Per-photo appearance: an affine colour transform per training photo (exposure and white balance).

Phones change exposure and white balance from shot to shot, so one surface point has different colours
in different photos. A single radiance field then learns their average and every photo is off by its own
gain. Here each training photo i gets ``pixel = A_i @ c + b_i`` on the colour the field renders (A_i 3x3,
b_i 3), starting at the identity and pulled back towards it by a small penalty: the field keeps the
neutral colour, the transforms absorb what differs between photos. It is the simplest model of what a
camera does to a whole image (a per-channel gain is its diagonal); NeRF-W's latent codes can also model
lighting that changes across the scene, which photos of one object taken minutes apart rarely need.

Three things live here and nowhere else:

* :class:`PhotoAppearance`, the trainable transforms (applied to the rendered rays in training by the piece
  :class:`recon.nerf.pieces.Appearance`);
* :func:`fit_affine`, the same transform fitted in closed form (ridge least squares towards the identity):
  held-out photos get theirs from their LEFT half and are scored on their RIGHT half (NeRF-W's protocol,
  :func:`recon.nerf.evaluate.held_out_right_half`), so the test pixels never shape what scores them;
* :func:`exposure_spread` / :func:`decide`, the automatic switch: the model is only used where the
  photos' brightness or colour balance changes between photos of the same surface.

The field itself never sees the transforms: rendering a mesh or a novel view uses the neutral appearance.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, Sequence

import numpy as np
import torch
from torch import Tensor, nn

__all__ = [
    "PhotoAppearance",
    "ExposureSpread",
    "fit_affine",
    "apply_affine",
    "to_neutral",
    "exposure_spread",
    "decide",
]

REG_WEIGHT = 1e-3
"""Penalty on the transforms' squared distance from the identity (per parameter, mean over photos)."""

THRESHOLD = 0.08
"""A photo whose estimated log gain (any channel) is more than this (≈ 8%) from the median photo's counts as changed."""

MIN_CHANGED_FRACTION = 0.1
"""The model switches on when at least this fraction of the photos (and at least 2) are changed."""

MIN_PAIR_FRACTION = 0.15
"""...and when at least this fraction of the matched pairs themselves differ by more than THRESHOLD: a true exposure
change shows in every pair it touches, while a few inconsistent pairs (specular highlights, glossy parts seen from
two sides, mismatches) spread by the least-squares fit over their photos do not. The bar sits between the glossy,
constant-exposure Lego and the fox's phone photos (benchmarks/results/exposure_pairs.json)."""

NEIGHBOURS = 4
"""Each photo is matched with this many nearest cameras (by position and viewing direction)."""

FAR_PARTNERS = 4
"""...and with this many more drawn at random among the cameras facing within FAR_MAX_ANGLE of it: a phone's exposure
that drifts as it follows the light round an object changes little between neighbouring photos, much between photos
further apart, so neighbours alone read a drift as constant."""

FAR_MAX_ANGLE = 60.0
"""Degrees between two cameras' viewing directions beyond which they rarely share enough of the object to match."""

MIN_MATCHES = 20
"""A pair measures its photos' gain ratio from at least this many SIFT matches of unclipped colour."""


class PhotoAppearance(nn.Module):
    """Per-photo affine colour transforms ``A_i c + b_i``, identity at initialization.

    Args:
        n_images: number of training photos (the batcher's image indices index them).
        kind: "affine" (3x3 matrix + bias) or "gain" (per-channel gain + bias).
        include_background: True when the photos' own backdrop went through the camera too (plain
            photos): the whole composited pixel is transformed. False for photos with alpha, whose
            background is a colour recon composites in: only the field's contribution is transformed.
        reg_weight: weight of the pull towards the identity.
    """

    def __init__(self, n_images: int, kind: Literal["affine", "gain"] = "affine", include_background: bool = True,
                 reg_weight: float = REG_WEIGHT) -> None:
        super().__init__()
        if n_images <= 0:
            raise ValueError(f"PhotoAppearance needs at least one photo, got {n_images}")
        if kind not in ("affine", "gain"):
            raise ValueError(f"appearance kind must be 'affine' or 'gain', got {kind!r}")
        self.kind, self.include_background, self.reg_weight = kind, include_background, reg_weight
        self.delta = nn.Parameter(torch.zeros(n_images, 3, 3) if kind == "affine" else torch.zeros(n_images, 3))
        self.bias = nn.Parameter(torch.zeros(n_images, 3))

    @property
    def n_images(self) -> int:
        return int(self.bias.shape[0])

    def matrices(self) -> Tensor:
        """(n, 3, 3) colour matrices A_i."""
        eye = torch.eye(3, device=self.delta.device, dtype=self.delta.dtype)
        return eye + (self.delta if self.kind == "affine" else torch.diag_embed(self.delta))

    def forward(self, out: dict[str, Any], image: Tensor) -> Tensor:
        """The rendered rays' colours (B, 3) as photo ``image`` (B,) long would show them.

        ``out`` is a model's render_rays result: rgb (B, 3), and for include_background=False also
        opacity (B,) and background (B, 3) (the field's part is rgb - (1 - opacity) * background).
        """
        a, b = self.matrices()[image], self.bias[image]
        rgb = out["rgb"].float()
        if self.include_background:
            return torch.einsum("bij,bj->bi", a, rgb) + b
        remainder = (1.0 - out["opacity"].float()).clamp_min(0.0)[:, None]
        bg = out["background"].float()
        fg = rgb - remainder * bg
        return torch.einsum("bij,bj->bi", a, fg) + b * (1.0 - remainder) + remainder * bg

    def regularizer(self) -> Tensor:
        """reg_weight × mean squared distance of the parameters from the identity transform."""
        return self.reg_weight * (self.delta.square().sum() + self.bias.square().sum()) / self.n_images

    def summary(self, names: Sequence[str]) -> dict[str, dict[str, Any]]:
        """Per photo: its diagonal gains, matrix and bias (rounded), for metrics and field files."""
        with torch.no_grad():
            a, b = self.matrices().cpu().double(), self.bias.cpu().double()
        return {n: {"gain": [round(float(v), 4) for v in torch.diagonal(a[i])],
                    "matrix": [[round(float(v), 5) for v in row] for row in a[i]],
                    "bias": [round(float(v), 5) for v in b[i]]}
                for i, n in enumerate(names)}


def to_neutral(image: np.ndarray, transform: dict[str, Any] | None) -> np.ndarray:
    """A photo (H, W, 3|4) uint8 as the neutral appearance would show it: A^-1 (pixel - b) (alpha kept).

    ``transform``: the photo's entry of :meth:`PhotoAppearance.summary` (None: returned as is). Colours baked
    from photos onto a mesh then agree with each other and with the field's own (neutral) colours.
    """
    if transform is None:
        return image
    a = np.asarray(transform["matrix"], np.float64)
    b = np.asarray(transform["bias"], np.float64)
    rgb = image[..., :3].astype(np.float64) / 255.0
    neutral = (rgb - b) @ np.linalg.inv(a).T
    out = image.copy()
    out[..., :3] = np.round(np.clip(neutral, 0.0, 1.0) * 255.0).astype(np.uint8)
    return out


# ----------------------------------------------------------------------------- closed-form fit
def _design(rgb: np.ndarray, opacity: np.ndarray | None, background: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4) regressors and (N, 3) background offset so that pixel = [c, s] @ W + offset is affine in W."""
    rgb = rgb.reshape(-1, 3).astype(np.float64)
    if opacity is None:
        return np.concatenate([rgb, np.ones((rgb.shape[0], 1))], axis=1), np.zeros_like(rgb)
    op = opacity.reshape(-1, 1).astype(np.float64)
    offset = (1.0 - op) * np.asarray(background, dtype=np.float64).reshape(-1, 3)
    return np.concatenate([rgb - offset, op], axis=1), offset


def fit_affine(pred: np.ndarray, target: np.ndarray, *, opacity: np.ndarray | None = None,
               background: np.ndarray | None = None, ridge: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The affine colour transform (A (3, 3), b (3,)) that best maps rendered ``pred`` onto ``target``.

    Ridge least squares towards the identity (``ridge`` × number of pixels), so a flat or tiny region cannot
    produce a wild transform. pred, target: (..., 3) in [0, 1]. With ``opacity`` (...,) and ``background``
    (3,) or (..., 3) only the field's part is transformed (photos with alpha, see :class:`PhotoAppearance`).
    """
    x, offset = _design(pred, opacity, background)
    y = target.reshape(-1, 3).astype(np.float64) - offset
    lam = ridge * x.shape[0]
    w0 = np.vstack([np.eye(3), np.zeros((1, 3))])
    w = np.linalg.solve(x.T @ x + lam * np.eye(4), x.T @ y + lam * w0)
    return w[:3].T, w[3]


def apply_affine(pred: np.ndarray, a: np.ndarray, b: np.ndarray, *, opacity: np.ndarray | None = None,
                 background: np.ndarray | None = None) -> np.ndarray:
    """``pred`` (..., 3) through the transform from :func:`fit_affine`, clipped to [0, 1]."""
    x, offset = _design(pred, opacity, background)
    w = np.vstack([a.T, b[None]])
    return np.clip(x @ w + offset, 0.0, 1.0).reshape(pred.shape).astype(np.float32)


# ----------------------------------------------------------------------------- automatic switch
@dataclass
class ExposureSpread:
    """Each photo's exposure relative to the others, estimated from the colours of matched points.

    log_gain: (n, 3) per-photo, per-channel log gain relative to the median photo (0: like most photos);
    per_photo: (n,) its largest |log gain|; pairs: how many pairs (neighbours and far partners) had enough matches;
    pairs_changed: how many of those differ by more than ``threshold`` themselves; neighbours, far: how the pairs
    were chosen (each photo's nearest cameras, and its partners further off).
    """

    log_gain: np.ndarray
    per_photo: np.ndarray
    threshold: float
    changed: int
    pairs: int
    pairs_changed: int = 0
    neighbours: int = NEIGHBOURS
    far: int = FAR_PARTNERS

    @property
    def n(self) -> int:
        return int(self.per_photo.size)

    @property
    def largest(self) -> float:
        return float(self.per_photo.max()) if self.n else 0.0

    @property
    def median(self) -> float:
        return float(np.median(self.per_photo)) if self.n else 0.0


def _float_rgb(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) float in [0, 1], usable (H, W) bool: opaque where the photo has alpha)."""
    img = image.astype(np.float32)
    if image.dtype == np.uint8:
        img /= 255.0
    usable = img[..., 3] > 0.5 if img.shape[-1] == 4 else np.ones(img.shape[:2], bool)
    return img[..., :3], usable


def _features(rgb: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """SIFT keypoints (K, 2) x, y, descriptors, and each keypoint's mean colour (K, 3) over a 5x5 patch (NaN where
    the patch touches transparent pixels)."""
    import cv2

    grey = cv2.cvtColor((rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
    kps, desc = cv2.SIFT_create(nfeatures=1500).detectAndCompute(grey, usable.astype(np.uint8) * 255)
    xy = np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2)
    blurred = cv2.blur(rgb, (5, 5))
    whole = cv2.blur(usable.astype(np.float32), (5, 5)) > 0.999  # patches with no transparent pixel
    ij = np.round(xy).astype(int)
    ij[:, 0] = ij[:, 0].clip(0, rgb.shape[1] - 1)
    ij[:, 1] = ij[:, 1].clip(0, rgb.shape[0] - 1)
    colour = np.where(whole[ij[:, 1], ij[:, 0]][:, None], blurred[ij[:, 1], ij[:, 0]], np.nan)
    return xy, desc, colour


def _pair_log_ratio(a: tuple, b: tuple, min_matches: int = MIN_MATCHES) -> np.ndarray | None:
    """Median per-channel log(colour in a / colour in b) over a's and b's SIFT matches (ratio test), or None."""
    import cv2

    if a[1] is None or b[1] is None or len(a[1]) < 2 or len(b[1]) < 2:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a[1], b[1], k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
    if len(good) < min_matches:
        return None
    ca = a[2][[m.queryIdx for m in good]]
    cb = b[2][[m.trainIdx for m in good]]
    with np.errstate(invalid="ignore"):  # NaN: a patch touching transparent pixels
        ok = ((ca > 0.03) & (ca < 0.97) & (cb > 0.03) & (cb < 0.97)).all(axis=1)  # no clipped or black pixels
    if ok.sum() < min_matches:
        return None
    return np.median(np.log(ca[ok]) - np.log(cb[ok]), axis=0)


def exposure_spread(images: Sequence[np.ndarray], c2w: np.ndarray, neighbours: int = NEIGHBOURS,
                    threshold: float = THRESHOLD, far: int = FAR_PARTNERS) -> ExposureSpread:
    """Per-photo exposure (log gain per channel) from the colours of the same points in photos that see them.

    Each photo is matched (SIFT, ratio test) with its ``neighbours`` nearest cameras (distance between
    centres plus the angle between viewing directions) and ``far`` cameras further away that face the same way
    (drawn with a fixed seed, so a run is repeatable): a matched point is the same surface seen twice, so
    the median log ratio of its colours in the two photos is the ratio of their gains, whatever the
    content. The gains then come from all pairs by least squares (relative to the median photo).
    Scene content that differs between views (the weakness of comparing mean brightness) does not enter.
    """
    n = len(images)
    if n < 3:
        return ExposureSpread(np.zeros((n, 3)), np.zeros(n), threshold, 0, 0, 0, neighbours, far)
    from recon.nerf.device import cpu_threads

    with ThreadPoolExecutor(max_workers=cpu_threads()) as pool:  # OpenCV's SIFT lets go of the GIL
        feats = list(pool.map(lambda im: _features(*_float_rgb(im)), images))
    c2w = np.asarray(c2w, dtype=np.float64)
    pos, fwd = c2w[:, :3, 3], -c2w[:, :3, 2]
    scale = float(np.median(np.linalg.norm(pos - pos.mean(axis=0), axis=1))) or 1.0
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1) / scale + np.arccos(np.clip(fwd @ fwd.T, -1.0, 1.0))
    np.fill_diagonal(dist, np.inf)
    edges = {tuple(sorted((i, int(j)))) for i in range(n) for j in np.argsort(dist[i])[: min(neighbours, n - 1)]}
    rng = np.random.default_rng(0)
    facing = fwd @ fwd.T > np.cos(np.radians(FAR_MAX_ANGLE))
    for i in range(n):
        others = [j for j in np.flatnonzero(facing[i]) if j != i and (min(i, j), max(i, j)) not in edges]
        edges.update((min(i, int(j)), max(i, int(j))) for j in rng.permutation(others)[:far])
    rows, rhs = [], []
    for i, j in sorted(edges):
        r = _pair_log_ratio(feats[i], feats[j])
        if r is not None:
            row = np.zeros(n)
            row[i], row[j] = 1.0, -1.0
            rows.append(row)
            rhs.append(r)
    if not rows:
        return ExposureSpread(np.zeros((n, 3)), np.zeros(n), threshold, 0, 0, 0, neighbours, far)
    # gauge: the mean log gain is 0 (lstsq's minimum-norm solution also pins unconnected photos at 0)
    g = np.linalg.lstsq(np.vstack([*rows, np.ones(n)]), np.vstack([*rhs, np.zeros(3)]), rcond=None)[0]
    g -= np.median(g, axis=0)
    per_photo = np.abs(g).max(axis=1)
    pairs_changed = int((np.abs(np.vstack(rhs)).max(axis=1) > threshold).sum())
    return ExposureSpread(g, per_photo, threshold, int((per_photo > threshold).sum()), len(rows), pairs_changed,
                          neighbours, far)


def decide(setting: str, spread: ExposureSpread) -> tuple[bool, str]:
    """(use the appearance model?, why) for train.appearance = auto | on | off."""
    stat = (f"{spread.changed} of {spread.n} photos have an exposure or colour balance more than {spread.threshold:.2f} "
            f"(log gain) from the median photo's, measured on the colours of SIFT matches in {spread.pairs} pairs of "
            f"photos, each with its {spread.neighbours} nearest and up to {spread.far} further off facing its way (largest "
            f"{spread.largest:.3f}, median {spread.median:.3f}); {spread.pairs_changed} of those pairs differ by more "
            f"than {spread.threshold:.2f} themselves")
    if setting == "on":
        return True, f"per-photo appearance on (train.appearance=on); {stat}"
    if setting == "off":
        return False, f"per-photo appearance off (train.appearance=off); {stat}"
    if setting != "auto":
        raise ValueError(f"train.appearance must be auto, on or off, got {setting!r}")
    if spread.pairs == 0:
        return False, ("per-photo appearance off: the photos' exposure could not be measured (no two nearby photos "
                       f"share {MIN_MATCHES} SIFT matches of unclipped colour); train.appearance=on models it all the same")
    need = max(2, int(np.ceil(MIN_CHANGED_FRACTION * spread.n)))
    need_pairs = max(1, int(np.ceil(MIN_PAIR_FRACTION * spread.pairs)))
    if spread.changed >= need and spread.pairs_changed >= need_pairs:
        return True, f"per-photo appearance on: exposure/white balance changes between photos ({stat})"
    return False, f"per-photo appearance off: the photos' exposure looks constant ({stat}; needs {need} photos and {need_pairs} pairs)"
