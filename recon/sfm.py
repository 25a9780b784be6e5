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

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from PIL import Image

from recon.colmap import pycolmap_logging_to, reconstruction_frames
from recon.errors import ReconError
from recon.images import device_of
from recon.scene import spread_evenly

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
    """Worker threads for extraction, matching and mapping; -1 uses every core."""
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
    """Names of the images left out of the model, in input order."""
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


def camera_groups(
    sizes: list[tuple[int, int]], devices: list[str | None], shared: bool, shared_intrinsics: str = "auto"
) -> list[list[int]]:
    """Indices of the images that share one set of intrinsics, in input order.

    All images when `shared`; else, under "auto", the images of one EXIF device and one size share a camera
    (two phones with the same resolution still get two), and an image without EXIF device gets its own
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
    on photos SfM dropped: twice the features, SIFT on the image upsampled 2× (first octave -1: extraction at
    a higher resolution, small detail), a lower peak threshold (low-contrast texture), a looser ratio test,
    and guided matching (more inliers once the two-view geometry is known)."""

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


def attempts_for(sizes: list[tuple[int, int]], attempts: tuple[Attempt, ...] = ATTEMPTS) -> tuple[Attempt, ...]:
    """The attempts for photos of these sizes: small photos (longest side <= SMALL_PHOTO_SIDE) extract at 2x
    resolution first, and at native resolution next if that left photos out (on the 160x120 frames of the
    video test the 2x attempt once registered 3 of 43 frames where native resolution registers all: COLMAP's
    multi-threaded mapper is not deterministic); larger photos keep native resolution (4x the pixels would
    cost more than the detail they add)."""
    if sizes and max(max(w, h) for w, h in sizes) <= SMALL_PHOTO_SIDE and attempts[0].first_octave >= 0:
        return (replace(attempts[0], name="default, 2× resolution", first_octave=-1),) + attempts
    return attempts


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
    attempt: Attempt = ATTEMPTS[0],
) -> None:
    """SIFT features into `database`, one COLMAP camera per group of `camera_groups` (EXIF focal priors read)."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = options.max_features * attempt.feature_factor
    extraction.sift.first_octave = attempt.first_octave
    if attempt.peak_threshold is not None:
        extraction.sift.peak_threshold = attempt.peak_threshold
    reader = pycolmap.ImageReaderOptions(camera_model=model)
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


def _too_few_message(num_registered: int, num_images: int, need: int) -> str:
    return (
        f"Structure from motion registered only {num_registered} of {num_images} photos "
        f"(at least {need} needed), so their camera positions could not be recovered. "
        "COLMAP needs each photo to share plenty of recognizable detail with others: take photos "
        "with more overlap (move a little between shots, about 10-20 degrees around the object), "
        "of a subject with more texture (plain walls, glass and shiny surfaces have too little), "
        "sharper (steady the camera, avoid motion blur), or simply more photos."
    )


def _map(
    database: Path, image_dir: Path, models_dir: Path, options: SfmOptions, needed: int, relaxed: bool
) -> pycolmap.Reconstruction | None:
    """Incremental mapping; returns the model with the most registered images, or None.

    relaxed lowers the inliers needed to start a model (100 -> 50) and to register an image
    (30 -> 15): still RANSAC-verified, but reachable with a few hundred features per image.
    """
    import pycolmap

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    mapping.min_model_size = max(2, min(mapping.min_model_size, needed))  # keep small photo sets
    if relaxed:
        mapping.mapper.init_min_num_inliers = 50
        mapping.mapper.abs_pose_min_num_inliers = 15
    shutil.rmtree(models_dir, ignore_errors=True)
    models_dir.mkdir(parents=True)
    models = pycolmap.incremental_mapping(database, image_dir, models_dir, options=mapping)
    return max(models.values(), key=lambda r: r.num_reg_images(), default=None)


ROBUST_LOSS_SCALE_PX = 0.5
"""Cauchy scale of the final bundle adjustment: observations a few times the usual 0.3 px error count less."""


def refine_robust(reconstruction: pycolmap.Reconstruction, scale_px: float = ROBUST_LOSS_SCALE_PX) -> dict:
    """One more global bundle adjustment of `reconstruction` (in place) with a Cauchy loss; returns what changed.

    COLMAP's bundle adjustment minimises squared reprojection error, so the few matches that are off by a pixel
    or two pull the shared focal length and k1, which the data barely constrain when every camera looks at the
    object from about the same distance. On rendered captures with a known pinhole camera (f = 482.8 px) a
    Cauchy loss at 0.5 px moved the focal from 473.3 to 478.9 px (hole scene) and from 478.8 to 481.4 px (the
    shipped sample): the object's scale error that follows halves.
    """
    import pycolmap

    def focal() -> float:
        return float(np.median([cam.mean_focal_length() for cam in reconstruction.cameras.values()]))

    before = {"focal_before": focal(), "error_before_px": float(reconstruction.compute_mean_reprojection_error())}
    ba = pycolmap.BundleAdjustmentOptions()
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = scale_px
    pycolmap.bundle_adjustment(reconstruction, ba)
    return {"loss": "cauchy", "scale_px": scale_px, **before, "focal_after": focal(),
            "error_after_px": float(reconstruction.compute_mean_reprojection_error())}


def run_sfm(
    image_dir: Path,
    names: list[str],
    work_dir: Path,
    options: SfmOptions,
    progress: ProgressFn | None = None,
    log_dir: Path | None = None,
) -> SfmResult:
    """Recover camera poses, intrinsics and sparse points for `names` (paths relative to image_dir).

    Writes work_dir/database.db (features and matches; any old one is replaced) and the largest
    model to work_dir/sparse/. Raises ReconError when fewer than options.min_registered images,
    or fewer than options.min_registered_fraction of them, get a pose.
    progress(phase, fraction) is called at the start and end of "extract", "match" and "map"
    (and with ("map", 0.5) when mapping is retried with relaxed thresholds). COLMAP's log files go to
    `log_dir` (see `pycolmap_logging_to`).
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

    pycolmap_logging_to(log_dir)
    # glog errors only: COLMAP's INFO and WARNING lines (thread counts, focal priors) are noise to users
    pycolmap.logging.minloglevel = max(int(pycolmap.logging.minloglevel), 2)
    pycolmap.set_random_seed(options.seed)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    device = pycolmap.Device.cpu
    timings: dict[str, float] = {"extract": 0.0, "match": 0.0, "map": 0.0}
    groups = camera_groups(sizes, exif_models, shared, options.shared_intrinsics)
    needed = max(options.min_registered, int(np.ceil(options.min_registered_fraction * len(names))))
    models_dir = work_dir / "models"

    attempts_here = attempts_for(sizes)
    if attempts_here[0] is not ATTEMPTS[0]:
        reason += (f" Features: SIFT at 2× resolution (first octave -1), the photos being at most {SMALL_PHOTO_SIDE} px"
                   " (native resolution next if that leaves photos out).")

    def run_attempt(attempt: Attempt) -> pycolmap.Reconstruction | None:
        retry = attempt is not attempts_here[0]
        database.unlink(missing_ok=True)  # a stale database would keep old images and features
        report("extract", 0.0)
        start = time.perf_counter()
        extract(database, image_dir, names, groups, model, options, attempt)
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
        best = _map(database, image_dir, models_dir, options, needed, relaxed=False)
        if best is None or best.num_reg_images() < len(names):
            # COLMAP's inlier thresholds suit thousands of features per image; small or plain photos
            # give hundreds, so retry with lower ones and keep whichever model registers more images.
            report("map", 0.5)
            relaxed = _map(database, image_dir, models_dir, options, needed, relaxed=True)
            if relaxed is not None and (best is None or relaxed.num_reg_images() > best.num_reg_images()):
                best = relaxed
        shutil.rmtree(models_dir, ignore_errors=True)
        timings["map"] += time.perf_counter() - start
        report("map", 1.0)
        return best

    best, attempts = register_best(run_attempt, len(names), options, attempts_here)
    num_registered = best.num_reg_images() if best is not None else 0
    if best is None or num_registered < needed:
        raise ReconError(_too_few_message(num_registered, len(names), needed))
    start = time.perf_counter()
    refinement = refine_robust(best)
    timings["map"] += time.perf_counter() - start

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
        dropped=[n for n in names if n not in frames],
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
    )
