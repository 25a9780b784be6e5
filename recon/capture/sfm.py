"""Structure from motion with pycolmap: camera poses, intrinsics and a sparse point cloud from photos.

`run_sfm` runs COLMAP's classical chain on CPU (SIFT extraction, exhaustive or sequential matching,
incremental mapping) and converts the largest model into our conventions:

- poses: COLMAP gives world->camera in OpenCV axes (camera looks down +Z, +Y down); we return
  camera-to-world 4x4 matrices in the OpenGL convention (camera looks down -Z, +Y up, +X right),
  still in COLMAP's (arbitrary similarity) world frame -- the normalize stage fixes scale and up;
- intrinsics: fl_x, fl_y, cx, cy (pixels, for the images in `image_dir` as given) and the
  OpenCV-style distortion k1, k2, p1, p2 of the transforms.json convention.

The database (`work_dir/database.db`) is the cache of features and matches; the chosen model is
written to `work_dir/sparse/` so other tools can open it.
"""
from __future__ import annotations

import contextlib
import copy
import os
import shutil
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from PIL import Image

from recon.capture.colmap import reconstruction_frames
from recon.capture.images import device_of
from recon.capture.scene import spread_evenly
from recon.errors import ReconError

if TYPE_CHECKING:  # pycolmap is imported when SfM runs: loading options (recon.config) must not pay for it
    import pycolmap

ProgressFn = Callable[[str, float], None]

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
EXHAUSTIVE_MAX_IMAGES = 150  # "auto" matcher: exhaustive up to here (quadratic cost), sequential above


@dataclass
class SfmOptions:
    """How to run structure from motion; the defaults suit an object captured by a phone."""

    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Pairs to match. auto: exhaustive up to 150 images, else sequential (photos ordered by name); always
    sequential for the frames of a video (they are in order)."""
    sequential_overlap: int = 10
    """Sequential matcher: each image is matched with this many following images (by name)."""
    loop_keyframes: int = 30
    """Sequential matcher's loop closure: this many images spread over the sequence are also matched with each
    other (where the end of a walk around the object meets its start); 0: off. COLMAP's own loop detection
    needs a vocabulary-tree file that cannot be downloaded offline."""
    max_features: int = 8192
    """Most SIFT features kept per image."""
    camera_model: Literal["auto", "SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL"] = "auto"
    """COLMAP camera model. auto: SIMPLE_RADIAL (one focal length, one radial distortion term)."""
    shared_intrinsics: Literal["auto", "yes", "no"] = "auto"
    """One camera for all images. auto: yes when all images have one size (and one EXIF camera model)."""
    num_threads: int = -1
    """Worker threads for extraction, matching, mapping and the final bundle adjustment; -1 uses every core."""
    seed: int = 0
    """Random seed for COLMAP's RANSAC and mapper."""
    min_registered: int = 3
    """Fail when fewer images than this register."""
    min_registered_fraction: float = 0.5
    """Fail when fewer than this fraction of the images register."""


@dataclass
class SfmResult:
    """The largest reconstructed model, in COLMAP's world frame with OpenGL camera axes."""

    camera_model: str
    shared_intrinsics: bool
    choice_reason: str
    """One sentence saying which camera model and sharing were used, and why (printed by the stage)."""
    registered: list[str]
    """Names of the images that got a pose, in input order."""
    dropped: list[str]
    """Names of the images SfM could not register, in input order."""
    frames: dict[str, dict]
    """name -> {"c2w": 4x4 nested list (OpenGL camera-to-world), "fl_x", "fl_y", "cx", "cy" (pixels),
    "w", "h" (pixels), "k1", "k2", "p1", "p2", "k3", "k4", "camera_model"} for each registered image."""
    points_xyz: np.ndarray
    """(P, 3) float64 sparse points, world frame."""
    points_rgb: np.ndarray
    """(P, 3) uint8 colors of the sparse points."""
    points_error: np.ndarray
    """(P,) float64 mean reprojection error of each point, pixels."""
    points_visible: dict[str, np.ndarray]
    """name -> (K,) int64 indices into points_xyz of the points that image observes (for near/far)."""
    mean_reprojection_error: float
    """Pixels, over all observations of the model."""
    num_points: int
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds spent in "extract", "match" and "map"."""
    num_cameras: int = 1
    """Distinct intrinsics estimated (one per device and size, or one per image)."""
    attempts: list[dict] = field(default_factory=list)
    """Each registration attempt: {"name", "settings", "registered"}; a retry runs only when photos were dropped."""
    refinement: dict = field(default_factory=dict)
    """The final robust bundle adjustment: {"loss", "scale_px", "focal_before", "focal_after", "error_before_px",
    "error_after_px"} (median focal over the cameras, pixels)."""
    excluded: dict[str, str] = field(default_factory=dict)
    """Registered images whose pose disagrees with the rest (see `pose_outliers`), left out of the model:
    name -> reason, in input order. They are in neither `registered` nor `dropped`."""
    groups_apart: list[list[str]] = field(default_factory=list)
    """The dropped images COLMAP posed as models of their own, each in input order, largest first: the capture fell
    apart into groups that share too few matches, which photos taken from between their viewpoints mend."""


def choose_camera(
    sizes: list[tuple[int, int]],
    exif_models: list[str | None],
    camera_model: str = "auto",
    shared_intrinsics: str = "auto",
) -> tuple[str, bool, str]:
    """Pick the COLMAP camera model and whether all images share one camera; say why in a sentence.

    sizes: (width, height) in pixels per image; exif_models: EXIF device ("Make Model") per image or None.
    Sharing one camera is right when one device took every photo: then all sizes match. A mix of
    sizes (or of EXIF devices) means several cameras or crops: see `camera_groups` for who shares.
    """
    if not sizes:
        raise ValueError("no images")
    model = "SIMPLE_RADIAL" if camera_model == "auto" else camera_model
    if model not in CAMERA_MODELS:
        raise ValueError(f"unknown camera model {model!r}; use one of {', '.join(CAMERA_MODELS)}")
    distinct_sizes = sorted(set(sizes))
    known_models = sorted({m for m in exif_models if m})
    one_size = len(distinct_sizes) == 1
    one_device = len(known_models) <= 1
    size_text = f"{distinct_sizes[0][0]}x{distinct_sizes[0][1]}" if one_size else f"{len(distinct_sizes)} sizes"
    if shared_intrinsics == "yes":
        if not one_size:
            raise ReconError(
                f"shared_intrinsics = \"yes\" needs every photo to have one size, but they come in {size_text} "
                f"({', '.join(f'{w}x{h}' for w, h in distinct_sizes[:5])}). Set shared_intrinsics to "
                "\"auto\" or \"no\", or resize/crop the photos to one size."
            )
        shared, why = True, "as configured"
    elif shared_intrinsics == "no":
        shared, why = False, "as configured"
    elif shared_intrinsics == "auto":
        shared = one_size and one_device
        if shared:
            device = f" from one camera ({known_models[0]})" if known_models else ""
            why = f"all {len(sizes)} images are {size_text}{device}"
        elif not one_size:
            why = f"the images come in {size_text}"
        else:
            why = f"the images come from {len(known_models)} cameras ({', '.join(known_models)})"
    else:
        raise ValueError(f"shared_intrinsics must be auto, yes or no, got {shared_intrinsics!r}")
    model_why = {
        "SIMPLE_PINHOLE": "one focal length, no distortion",
        "PINHOLE": "two focal lengths, no distortion",
        "SIMPLE_RADIAL": "one focal length and one radial distortion term, estimated",
        "RADIAL": "one focal length and two radial distortion terms, estimated",
        "OPENCV": "two focal lengths, radial and tangential distortion, estimated",
    }[model]
    model_src = "the default" if camera_model == "auto" else "as configured"
    groups = camera_groups(sizes, exif_models, shared, shared_intrinsics)
    if shared:
        sharing = "One shared"
    elif len(groups) < len(sizes):
        sharing = f"{len(groups)} (one per device and image size)"
    else:
        sharing = "One per-image"
    reason = f"{sharing} {model} camera ({model_why}; {model_src}): {why}."
    return model, shared, reason


def turned_to_share(sizes: list[tuple[int, int]]) -> list[bool]:
    """Which photos SfM sees turned a quarter: those taken the other way up (w×h where more photos are h×w; on a tie
    the landscape ones), so that one camera's intrinsics hold both, a COLMAP camera having one width and height."""
    count = Counter(sizes)
    return [w != h and (count[(h, w)], w) > (count[(w, h)], h) for w, h in sizes]


def camera_groups(
    sizes: list[tuple[int, int]], devices: list[str | None], shared: bool, shared_intrinsics: str = "auto"
) -> list[list[int]]:
    """Indices of the images that share one set of intrinsics, in input order.

    All images when `shared`; else, under "auto", the images of one EXIF device and one size share a camera
    (two phones with the same resolution still get two, and so do two lenses or zooms of one phone, since
    `recon.capture.images.device_of` names the focal length too), and an image without EXIF device gets its own
    (a crop or an edited copy cannot be told from another lens).
    """
    if shared:
        return [list(range(len(sizes)))]
    groups: dict[object, list[int]] = {}
    for i, (size, device) in enumerate(zip(sizes, devices, strict=True)):
        key = (size, device) if device and shared_intrinsics == "auto" else ("image", i)
        groups.setdefault(key, []).append(i)
    return list(groups.values())


def _image_info(image_dir: Path, names: list[str]) -> tuple[list[tuple[int, int]], list[str | None]]:
    """(width, height) in stored pixels and EXIF device ("Make Model", or None) per image, reading headers only."""
    sizes: list[tuple[int, int]] = []
    for name in names:
        path = image_dir / name
        try:
            with Image.open(path) as im:
                sizes.append((int(im.width), int(im.height)))
        except (OSError, ValueError) as exc:
            raise ReconError(f"cannot read image {path}: {exc}. Remove it or replace it with a JPEG or PNG.") from exc
    return sizes, [device_of(image_dir / name) for name in names]


@dataclass(frozen=True)
class Attempt:
    """One way to extract and match features. The retry finds more, and more reliable, correspondences
    on photos SfM dropped: twice the features, for small photos SIFT on the image upsampled 2× (first octave -1:
    extraction at a higher resolution, small detail; see `attempts_for`), a lower peak threshold (low-contrast
    texture), a looser ratio test, and guided matching (more inliers once the two-view geometry is known)."""

    name: str
    feature_factor: int = 1
    first_octave: int = 0
    peak_threshold: float | None = None
    max_ratio: float | None = None
    guided: bool = False

    def settings(self, options: SfmOptions) -> str:
        parts = [f"{options.max_features * self.feature_factor} features"]
        if self.first_octave < 0:
            parts.append("extraction at 2× resolution (first octave -1)")
        if self.peak_threshold is not None:
            parts.append(f"SIFT peak threshold {self.peak_threshold:g}")
        if self.max_ratio is not None:
            parts.append(f"ratio test {self.max_ratio:g}")
        if self.guided:
            parts.append("guided matching")
        return ", ".join(parts)


ATTEMPTS = (
    Attempt("default"),
    Attempt("more features", feature_factor=2, first_octave=-1, peak_threshold=0.004, max_ratio=0.85, guided=True),
)


SMALL_PHOTO_SIDE = 1000
"""Photos whose longest side is at most this many pixels get SIFT on the image upsampled 2x in the first
attempt too (first octave -1, COLMAP's own default): at native resolution small photos give about half the
points and a focal length several times further off, and a short focal length makes the object come out that
much too large after camera alignment."""


SMALL_CAPTURE = 50
"""Captures of at most this many (large) photos start with `THOROUGH`: matching them costs little, and a failed
pass followed by a retry cost a tester 5-8 minutes on 14 photos of 1600 px."""
THOROUGH = Attempt("thorough", max_ratio=0.85)
"""More correspondences for the price of one pass: the ratio test keeps more matches (RANSAC still verifies every
one). On 8 fox photos at 1600 px: 17 % more sparse points for 28 % more CPU time than the default; a lower SIFT
peak threshold added CPU time (more features to match) and no points, guided matching 3x the points for 7x the
matching time (20x on 14 photos)."""


def attempts_for(sizes: list[tuple[int, int]], attempts: tuple[Attempt, ...] = ATTEMPTS) -> tuple[Attempt, ...]:
    """The attempts for photos of these sizes, in order.

    Small photos (longest side <= SMALL_PHOTO_SIDE) extract at 2x resolution first, and at native resolution
    next if that left photos out (on the 160x120 frames of the video test the 2x attempt once registered 3 of
    43 frames where native resolution registers all: COLMAP's multi-threaded mapper is not deterministic).
    Larger photos keep native resolution in every attempt (4x the pixels would cost more than the detail they
    add), and a small capture of them (at most SMALL_CAPTURE) starts with `THOROUGH`.
    """
    if not sizes:
        return attempts
    if max(max(w, h) for w, h in sizes) <= SMALL_PHOTO_SIDE:
        if attempts[0].first_octave >= 0:
            return (replace(attempts[0], name="default, 2× resolution", first_octave=-1),) + attempts
        return attempts
    native = tuple(replace(a, first_octave=0) for a in attempts)
    if len(sizes) <= SMALL_CAPTURE:
        return (THOROUGH,) + native[1:]
    return native


def register_best(run_attempt: Callable[[Attempt], pycolmap.Reconstruction | None], total: int, options: SfmOptions,
                  attempts: tuple[Attempt, ...] = ATTEMPTS) -> tuple[pycolmap.Reconstruction | None, list[dict]]:
    """Run the attempts in order until one registers all `total` photos; the model registering most wins
    (ties: the later, whose features are the ones left in the database). Returns it and a log entry per attempt."""
    best, log = None, []
    for attempt in attempts:
        model = run_attempt(attempt)
        registered = model.num_reg_images() if model is not None else 0
        log.append({"name": attempt.name, "settings": attempt.settings(options), "registered": registered})
        if model is not None and (best is None or registered >= best.num_reg_images()):
            best = model
        if registered >= total:
            break
    return best, log


def extract(
    database: Path, image_dir: Path, names: list[str], groups: list[list[int]], model: str, options: SfmOptions,
    attempt: Attempt = ATTEMPTS[0], mask_dir: Path | None = None,
) -> None:
    """SIFT features into `database`, one COLMAP camera per group of `camera_groups` (EXIF focal priors read);
    with ``mask_dir``, only where its `NAME.png` masks are not black (COLMAP's feature masks)."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_features * attempt.feature_factor
    extraction.sift.first_octave = attempt.first_octave
    if attempt.peak_threshold is not None:
        extraction.sift.peak_threshold = attempt.peak_threshold
    reader = pycolmap.ImageReaderOptions(camera_model=model)
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    if all(len(g) == 1 for g in groups):
        calls = [(names, pycolmap.CameraMode.PER_IMAGE)]
    else:  # each call with SINGLE opens one new camera for its images
        calls = [([names[i] for i in g], pycolmap.CameraMode.SINGLE) for g in groups]
    for group_names, mode in calls:
        pycolmap.extract_features(
            database, image_dir, image_names=group_names, camera_mode=mode, reader_options=reader,
            extraction_options=extraction, device=pycolmap.Device.cpu,
        )


def _pick_matcher(matcher: str, num_images: int) -> str:
    if matcher == "auto":
        return "exhaustive" if num_images <= EXHAUSTIVE_MAX_IMAGES else "sequential"
    if matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"matcher must be auto, exhaustive or sequential, got {matcher!r}")
    return matcher


def loop_pairs(names: list[str], keyframes: int, overlap: int) -> list[tuple[str, str]]:
    """Loop-closure pairs for sequential matching: every two of `keyframes` images spread over the sequence
    (in name order, as COLMAP's sequential matcher orders them) that it would not pair already (more than
    `overlap` apart)."""
    ordered = sorted(names)
    if keyframes < 2:
        return []
    keys = spread_evenly(list(range(len(ordered))), keyframes)
    return [(ordered[a], ordered[b]) for i, a in enumerate(keys) for b in keys[i + 1 :] if b - a > overlap]


def _too_few_message(num_registered: int, num_images: int, need: int, groups: list[list[str]] | None = None) -> str:
    apart = ""
    if groups:
        sizes = " and ".join(str(len(g)) for g in groups)
        apart = (f" The rest fell apart into {len(groups)} more group{'s' if len(groups) > 1 else ''} posed on their "
                 f"own ({sizes} photos) that share too few matches with it: photos taken from viewpoints between the "
                 f"groups join them.")
    return (
        f"Structure from motion registered only {num_registered} of {num_images} photos "
        f"(at least {need} needed), so their camera positions could not be recovered.{apart} "
        "COLMAP needs each photo to share plenty of recognizable detail with others: take photos "
        "with more overlap (move a little between shots, about 10-20 degrees around the object), "
        "of a subject with more texture (plain walls, glass and shiny surfaces have too little), "
        "sharper (steady the camera, avoid motion blur), or simply more photos."
    )


def dropped_message(result: SfmResult, kept: int, label: Callable[[str], str] = str) -> str:
    """Which photos SfM left out and why, in a sentence: those posed apart as groups of their own, and those that
    matched too little; `label` names an image (the SfM copy's name -> the photo's)."""
    apart = {n for group in result.groups_apart for n in group}
    alone = [label(n) for n in result.dropped if n not in apart]
    if not result.groups_apart:
        return ", ".join(alone)
    plural = len(result.groups_apart) > 1
    counts = " and ".join(str(len(g)) for g in result.groups_apart)
    listed = "; ".join(", ".join(label(n) for n in g) for g in result.groups_apart)
    groups = f"{len(result.groups_apart)} separate groups" if plural else "a separate group"
    text = (f"{len(apart)} were posed as {groups} of their own ({counts} photos: {listed}) that "
            f"share{'' if plural else 's'} too few matches with the {kept} kept, so the field and mesh hold only what "
            f"the kept photos see")
    if alone:
        text += f"; {len(alone)} matched too little to be posed ({', '.join(alone)})"
    return text + (". Photos taken from viewpoints between the groups join them in one model: add them to the folder "
                   "and run again (photos taken after the object was moved or turned over never join the others: "
                   "run them as a capture of their own)")


GLOBAL_BA_TUNING: dict[str, Any] = {
    "ba_global_frames_ratio": 1.4, "ba_global_points_ratio": 1.4, "mapper.ba_global_ignore_redundant_points3D": True,
}
"""COLMAP's mapping options recon sets: a global bundle adjustment once the model has grown by 40% in frames or points
since the last (COLMAP's default is 10%), over the points that are not redundant. Why: on two cores the global
adjustments are most of the mapping of a long capture (a phone clip's ~150 frames), while the local adjustment after
each registration and recon's final robust adjustment of the whole model (`refine_robust`) keep the poses as accurate
(`benchmarks/sfm_mapping.py`)."""


def _set_option(options: Any, name: str, value: Any) -> bool:
    """Set a COLMAP option by dotted name ("mapper.ba_local_num_images"); False when there is no such option."""
    *path, key = name.split(".")
    target = options
    for part in path:
        target = getattr(target, part, None)
    if target is None or not hasattr(target, key):
        return False
    setattr(target, key, value)
    return True


def _map(
    database: Path, image_dir: Path, models_dir: Path, options: SfmOptions, needed: int, relaxed: bool,
    tuning: dict[str, Any] | None = None,
) -> tuple[pycolmap.Reconstruction | None, list[list[str]]]:
    """Incremental mapping: the model with the most registered images (or None), and the images of each other model
    COLMAP started (`models_apart`).

    relaxed lowers the inliers needed to start a model (100 -> 50) and to register an image
    (30 -> 15): still RANSAC-verified, but reachable with a few hundred features per image.
    tuning: COLMAP's mapping options set after recon's (`GLOBAL_BA_TUNING`), by dotted name, for
    `benchmarks/sfm_mapping.py` to weigh them on a capture's own database.
    """
    import pycolmap

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    mapping.min_model_size = max(2, min(mapping.min_model_size, needed))  # keep small photo sets
    if relaxed:
        mapping.mapper.init_min_num_inliers = 50
        mapping.mapper.abs_pose_min_num_inliers = 15
    for name, value in GLOBAL_BA_TUNING.items():
        _set_option(mapping, name, value)  # an older pycolmap without one keeps its default
    for name, value in (tuning or {}).items():
        if not _set_option(mapping, name, value):
            raise ValueError(f"COLMAP's mapping options have no {name!r}")
    shutil.rmtree(models_dir, ignore_errors=True)
    models_dir.mkdir(parents=True)
    models = pycolmap.incremental_mapping(database, image_dir, models_dir, options=mapping)
    ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    if not ranked:
        return None, []
    return ranked[0], models_apart(ranked[0], ranked[1:])


def posed_images(rec: pycolmap.Reconstruction) -> list[str]:
    """The names of the images `rec` gives a pose."""
    return [image.name for image in rec.images.values() if image.has_pose]


def models_apart(kept: pycolmap.Reconstruction, others: list[pycolmap.Reconstruction]) -> list[list[str]]:
    """The images of each model besides the kept one, less those the kept one poses too (COLMAP lets models share a
    few), largest first; groups left with fewer than 2 images are no group."""
    posed = set(posed_images(kept))
    groups = [sorted(set(posed_images(rec)) - posed) for rec in others]
    return sorted((g for g in groups if len(g) >= 2), key=len, reverse=True)


FAR_OFF_SPREADS = 3.0
"""A camera is far off when its centre is further than this many robust spreads (the median distance of the
centres from their median centre) from the median centre, and ..."""
ALONE_SPACINGS = 5.0
"""... its nearest camera further than this many usual spacings (the median nearest-camera distance). An orbit's
cameras are all about one spread out; the end cameras of a short walk along a facade can be three or four spreads
out, but a step or two from the next one (in 3000 simulated orbits and walks of 5-80 photos with steps varying
ninefold, no camera was both)."""
FEW_POINTS_FRACTION = 1 / 3
"""A camera seeing fewer than this fraction of the median camera's sparse points is weakly supported."""
HIGH_ERROR_FACTOR = 2.0
"""A camera whose mean reprojection error is over this many times the median camera's is poorly fitted."""
MIN_CAMERAS_TO_JUDGE = 5
"""Medians of fewer cameras say too little about what the rest agree on: nothing is left out below this."""


def pose_outliers(
    names: list[str], centres: np.ndarray, points_seen: np.ndarray, errors_px: np.ndarray
) -> dict[str, str]:
    """The cameras whose pose disagrees with the rest, each with the reason in a sentence.

    names: (N,); centres: (N, 3) camera centres, any similarity frame; points_seen: (N,) sparse points each
    camera observes; errors_px: (N,) each camera's mean reprojection error (NaN: none). A camera is left out
    when its centre is far off, from the middle and from every other camera (`FAR_OFF_SPREADS`,
    `ALONE_SPACINGS`), AND its pose is weakly supported (`FEW_POINTS_FRACTION` of the median camera's points)
    or poorly fitted (`HIGH_ERROR_FACTOR` times the median error): a misregistered photo hangs on a few
    matches, while a photo genuinely taken from further away still sees plenty.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    points_seen = np.asarray(points_seen, dtype=np.float64)
    errors_px = np.asarray(errors_px, dtype=np.float64)
    if not len(names) == len(centres) == len(points_seen) == len(errors_px):
        raise ValueError(f"{len(names)} names, {len(centres)} centres, {len(points_seen)} point counts and "
                         f"{len(errors_px)} errors: one of each per camera is needed")
    if len(names) < MIN_CAMERAS_TO_JUDGE:
        return {}
    from scipy.spatial import cKDTree  # loaded here: every command reads SfmOptions (the config), few need a tree

    distance = np.linalg.norm(centres - np.median(centres, axis=0), axis=1)
    spread = float(np.median(distance))
    gap = cKDTree(centres).query(centres, k=2)[0][:, 1]  # distance to the nearest other camera
    spacing = float(np.median(gap))
    if not (spread > 0.0 and spacing > 0.0):
        return {}
    median_points, median_error = float(np.median(points_seen)), float(np.nanmedian(errors_px))
    outliers = {}
    for i, name in enumerate(names):
        far, alone = distance[i] / spread, gap[i] / spacing
        if not (far > FAR_OFF_SPREADS and alone > ALONE_SPACINGS):
            continue
        weak = []
        if points_seen[i] < FEW_POINTS_FRACTION * median_points:
            weak.append(f"it sees {points_seen[i]:.0f} sparse points (median camera {median_points:.0f})")
        if not errors_px[i] <= HIGH_ERROR_FACTOR * median_error:  # NaN too
            weak.append(f"its reprojection error is {errors_px[i]:.2f} px (median {median_error:.2f} px)")
        if weak:
            outliers[name] = (f"its pose disagrees with the others: the camera sits {far:.1f}x the camera spread from "
                              f"the median camera centre ({alone:.0f}x the usual spacing from its nearest camera), and "
                              f"{' and '.join(weak)}")
    return outliers


def camera_support(rec: pycolmap.Reconstruction) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """Per registered image of `rec`: (names, (N, 3) centres, (N,) sparse points observed, (N,) mean reprojection
    error in pixels) -- what `pose_outliers` judges."""
    xyz_by_id = {point_id: point.xyz for point_id, point in rec.points3D.items()}
    names, centres, seen, errors = [], [], [], []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        observations = image.get_observation_points2D()
        error = float("nan")
        if len(observations):
            xy = np.array([obs.xy for obs in observations])
            world = np.array([xyz_by_id[obs.point3D_id] for obs in observations])
            projected = image.camera.img_from_cam(image.cam_from_world() * world, check_cheirality=False)
            error = float(np.mean(np.linalg.norm(projected - xy, axis=1)))
        names.append(image.name)
        centres.append(image.projection_center())
        seen.append(len(observations))
        errors.append(error)
    return names, np.reshape(centres, (-1, 3)), np.asarray(seen, dtype=np.int64), np.asarray(errors)


def leave_out_outliers(rec: pycolmap.Reconstruction) -> dict[str, str]:
    """Deregister (in place) the images whose pose `pose_outliers` rejects; returns name -> reason."""
    outliers = pose_outliers(*camera_support(rec))
    for name in outliers:
        image = rec.find_image_with_name(name)
        rec.deregister_frame(image.frame_id)
    return outliers


ROBUST_LOSS_SCALE_PX = 0.5
"""Cauchy scale of the final bundle adjustment: observations a few times the usual 0.3 px error count less."""
REFINE_KEEP_WORSE = 2.0
"""The final bundle adjustment is undone when it leaves the mean reprojection error over this many times what it
was (or not finite): on a degenerate model (every camera in one place) the solver can run away."""


def refine_robust(reconstruction: pycolmap.Reconstruction, scale_px: float = ROBUST_LOSS_SCALE_PX,
                  num_threads: int = -1) -> tuple[pycolmap.Reconstruction, dict]:
    """One more global bundle adjustment of `reconstruction` with a Cauchy loss; returns the model to keep (the
    adjusted one, or the one before where the adjustment ran away: `REFINE_KEEP_WORSE`) and what changed.
    num_threads: Ceres's threads (-1: every core), `SfmOptions.num_threads` as for the rest of SfM, so that a
    capture held to N cores in a batch stays there.

    COLMAP's bundle adjustment minimises squared reprojection error, so the few matches that are off by a pixel
    or two pull the shared focal length and k1, which the data barely constrain when every camera looks at the
    object from about the same distance. On rendered captures with a known pinhole camera (f = 482.8 px) a
    Cauchy loss at 0.5 px moved the focal from 473.3 to 478.9 px (hole scene) and from 478.8 to 481.4 px (the
    shipped sample): the object's scale error that follows halves.
    """
    import pycolmap

    def focal() -> float:
        return float(np.median([cam.mean_focal_length() for cam in reconstruction.cameras.values()]))

    unadjusted = copy.deepcopy(reconstruction)
    before = {"focal_before": focal(), "error_before_px": float(reconstruction.compute_mean_reprojection_error())}
    ba = pycolmap.BundleAdjustmentOptions()
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = scale_px
    ba.ceres.solver_options.num_threads = num_threads
    pycolmap.bundle_adjustment(reconstruction, ba)
    after = {"focal_after": focal(), "error_after_px": float(reconstruction.compute_mean_reprojection_error())}
    ran_away = not (np.isfinite(after["focal_after"]) and after["focal_after"] > 0
                    and after["error_after_px"] <= REFINE_KEEP_WORSE * before["error_before_px"])
    return (unadjusted if ran_away else reconstruction), {"loss": "cauchy", "scale_px": scale_px, **before, **after,
                                                          "undone": ran_away}


@contextlib.contextmanager
def native_output_to(log_file: Path | None) -> Iterator[None]:
    """While inside, everything COLMAP prints goes to the end of `log_file`, none of it to the terminal.

    COLMAP logs through glog onto file descriptor 2, and Ceres (its bundle adjuster) prints solver warnings
    ("Linear solver failure ... Eigen failure") there too, whatever glog's level flags say; so descriptor 2
    itself is pointed at the log file, and glog logs every level to it alone (no glog files of its own).
    Python's `sys.stderr` (recon's progress bars and messages) keeps writing to the terminal. None: COLMAP
    errors only, on stderr.
    """
    import pycolmap

    glog = pycolmap.logging
    flags = {name: getattr(glog, name) for name in ("minloglevel", "logtostderr", "stderrthreshold")}
    if log_file is None:
        glog.minloglevel = max(int(flags["minloglevel"]), 2)
        try:
            yield
        finally:
            glog.minloglevel = flags["minloglevel"]
        return
    log_file.parent.mkdir(parents=True, exist_ok=True)
    python_stderr = sys.stderr
    try:
        on_descriptor_2 = python_stderr.fileno() == 2
    except (AttributeError, OSError, ValueError):  # pytest's capture, a StringIO...: not the descriptor
        on_descriptor_2 = False
    python_stderr.flush()
    terminal = os.dup(2)
    with open(log_file, "ab") as log:
        os.dup2(log.fileno(), 2)
    try:
        if on_descriptor_2:
            sys.stderr = open(os.dup(terminal), "w", buffering=1, encoding=python_stderr.encoding,  # noqa: SIM115
                              errors=python_stderr.errors)
        glog.minloglevel, glog.logtostderr, glog.stderrthreshold = 0, True, 0
        yield
    finally:
        for name, value in flags.items():
            setattr(glog, name, value)
        if sys.stderr is not python_stderr:
            sys.stderr.close()
            sys.stderr = python_stderr
        os.dup2(terminal, 2)
        os.close(terminal)


def run_sfm(
    image_dir: Path,
    names: list[str],
    work_dir: Path,
    options: SfmOptions,
    progress: ProgressFn | None = None,
    log_file: Path | None = None,
    mask_dir: Path | None = None,
) -> SfmResult:
    """Recover camera poses, intrinsics and sparse points for `names` (paths relative to image_dir).

    Writes work_dir/database.db (features and matches; any old one is replaced) and the largest
    model, less the cameras whose pose disagrees with the rest (`leave_out_outliers`, before and after the final
    adjustment), to work_dir/sparse/.
    Raises ReconError when fewer than options.min_registered images, or fewer than
    options.min_registered_fraction of them, get a pose.
    progress(phase, fraction) is called at the start and end of "extract", "match" and "map"
    (and with ("map", 0.5) when mapping is retried with relaxed thresholds). Everything COLMAP prints is
    appended to `log_file` (see `native_output_to`). ``mask_dir``: features only where its masks allow (`extract`).
    """
    import pycolmap

    report: ProgressFn = progress if progress is not None else (lambda phase, fraction: None)
    image_dir, work_dir = Path(image_dir), Path(work_dir)
    names = list(names)
    if len(set(names)) != len(names):
        raise ValueError("image names must be unique")
    if len(names) < max(2, options.min_registered):
        raise ReconError(
            f"Structure from motion needs at least {max(2, options.min_registered)} photos, got {len(names)}. "
            "Take more photos of the subject from different viewpoints, with plenty of overlap between them."
        )
    sizes, exif_models = _image_info(image_dir, names)
    model, shared, reason = choose_camera(sizes, exif_models, options.camera_model, options.shared_intrinsics)
    matcher = _pick_matcher(options.matcher, len(names))

    pycolmap.set_random_seed(options.seed)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    device = pycolmap.Device.cpu
    timings: dict[str, float] = {"extract": 0.0, "match": 0.0, "map": 0.0}
    groups = camera_groups(sizes, exif_models, shared, options.shared_intrinsics)
    needed = max(options.min_registered, int(np.ceil(options.min_registered_fraction * len(names))))
    models_dir = work_dir / "models"

    attempts_here = attempts_for(sizes)
    if attempts_here[0].first_octave < 0:
        reason += (f" Features: SIFT at 2× resolution (first octave -1), the photos being at most {SMALL_PHOTO_SIDE} px"
                   " (native resolution next if that leaves photos out).")
    elif attempts_here[0] is THOROUGH:
        reason += (f" Features: {THOROUGH.settings(options)} from the first pass, a capture of at most {SMALL_CAPTURE}"
                   " photos being cheap to match.")

    def run_attempt(attempt: Attempt) -> pycolmap.Reconstruction | None:
        retry = attempt is not attempts_here[0]
        database.unlink(missing_ok=True)  # a stale database would keep old images and features
        report("extract", 0.0)
        start = time.perf_counter()
        extract(database, image_dir, names, groups, model, options, attempt, mask_dir)
        timings["extract"] += time.perf_counter() - start
        report("extract", 1.0)

        report("match", 0.0)
        start = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = options.num_threads
        matching.use_gpu = False
        matching.guided_matching = attempt.guided
        if attempt.max_ratio is not None:
            matching.sift.max_ratio = attempt.max_ratio
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=device)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = options.sequential_overlap
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=device)
            pairs = loop_pairs(names, options.loop_keyframes, options.sequential_overlap)
            if pairs:
                pair_file = work_dir / "loop_pairs.txt"
                pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
                imported = pycolmap.ImportedPairingOptions()
                imported.match_list_path = str(pair_file)
                pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=imported, device=device)
        timings["match"] += time.perf_counter() - start
        report("match", 1.0)

        report("map", 0.5 if retry else 0.0)
        start = time.perf_counter()
        best, apart = _map(database, image_dir, models_dir, options, needed, relaxed=False)
        if best is None or best.num_reg_images() < len(names):
            # COLMAP's inlier thresholds suit thousands of features per image; small or plain photos
            # give hundreds, so retry with lower ones and keep whichever model registers more images.
            report("map", 0.5)
            relaxed, relaxed_apart = _map(database, image_dir, models_dir, options, needed, relaxed=True)
            if relaxed is not None and (best is None or relaxed.num_reg_images() > best.num_reg_images()):
                best, apart = relaxed, relaxed_apart
        shutil.rmtree(models_dir, ignore_errors=True)
        timings["map"] += time.perf_counter() - start
        report("map", 1.0)
        mapped.append((best, apart))
        return best

    mapped: list[tuple[pycolmap.Reconstruction | None, list[list[str]]]] = []

    with native_output_to(log_file):
        best, attempts = register_best(run_attempt, len(names), options, attempts_here)
        apart = next((found for model, found in mapped if model is best), []) if best is not None else []
        posed_apart = [[n for n in names if n in members] for members in map(set, apart)]
        excluded = leave_out_outliers(best) if best is not None else {}
        num_registered = best.num_reg_images() if best is not None else 0
        if best is not None and num_registered >= needed:
            start = time.perf_counter()
            best, refinement = refine_robust(best, num_threads=options.num_threads)
            timings["map"] += time.perf_counter() - start
            # judged again: the final adjustment can carry a photo held by a few matches off the rest. Its few
            # observations barely pulled the other poses, so they are not adjusted once more.
            excluded.update(leave_out_outliers(best))
            num_registered = best.num_reg_images()
        if best is None or num_registered < needed:
            raise ReconError(_too_few_message(num_registered, len(names), needed, posed_apart))

    sparse_dir = work_dir / "sparse"
    shutil.rmtree(sparse_dir, ignore_errors=True)
    sparse_dir.mkdir()
    best.write(sparse_dir)

    frames, xyz, rgb, err, visible = reconstruction_frames(best, names)
    return SfmResult(
        camera_model=model,
        shared_intrinsics=shared,
        choice_reason=reason,
        registered=[n for n in names if n in frames],
        dropped=[n for n in names if n not in frames and n not in excluded],
        frames=frames,
        points_xyz=xyz,
        points_rgb=rgb,
        points_error=err,
        points_visible=visible,
        mean_reprojection_error=float(best.compute_mean_reprojection_error()),
        num_points=int(xyz.shape[0]),
        timings=timings,
        num_cameras=len(groups),
        attempts=attempts,
        refinement=refinement,
        excluded={n: excluded[n] for n in names if n in excluded},
        groups_apart=posed_apart,
    )
