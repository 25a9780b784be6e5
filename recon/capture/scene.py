"""The scene contract: cameras, sparse points, box, split and frame transform — and imports into it.

`scene.json` is a transforms.json (instant-ngp / nerfstudio convention: OpenGL camera-to-world
`transform_matrix`, `fl_x fl_y cx cy w h`, OpenCV distortion `k1 k2 p1 p2`, `file_path`) with our own
keys: `aabb`, `capture`, per-frame `near`/`far`/`split`, and `world_from_source` / `source_from_world`
(the similarity between the SfM/import frame and ours), so other tools can read it and meshes can
be returned to the original frame. A photo in the input's folder (or beside it, as its masks are) is stored as
`{source}/NAME` (`SOURCE_MARK`, `stored_path`) and found in the folder the input is read from now, so a scene still
holds when its photos move; images recon wrote are relative to the scene folder, anything else is absolute.

The poses stage writes a `Scene` in the source frame (identity transform, no box); normalize writes
the canonical one. Every import (COLMAP model, transforms.json, NeRF-synthetic splits, `.npz`) ends
up as the same `Scene`, so nothing downstream knows where the poses came from.
"""
from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.atomic import read_json, write_json_atomic
from recon.capture.colmap import LENS_MODELS, find_colmap_model, read_model, reconstruction_frames
from recon.capture.images import (IMAGE_SUFFIXES, MIN_SIDE, check_photo_headers, check_photo_set, list_photos,
                                  no_photos, oriented_size, read_mask, undistort)
from recon.errors import InputError

SCENE_FORMAT = "recon-scene"
SCENE_VERSION = 1
Split = Literal["train", "val", "test"]
SPLITS: tuple[str, ...] = ("train", "val", "test")
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", "k3", "k4", "camera_model")

SOURCE_MARK = "{source}"
"""How a stored path starts when it names a file in (or beside) the input's folder: `Scene.source` resolves it."""

RAY_DISTANCE = "distance along the unit-length ray"
"""What a frame's `near` and `far` measure, everywhere in recon: the distance t along a ray with a unit-length
direction (the rays of `recon.nerf.rays`), so `o + t·d` at t = far is as far from the camera for a corner
pixel as for the centre one. Not the depth along the optical axis: a corner ray reaching depth z has
travelled z / cos(angle off-axis). `recon.capture.normalization` computes them as Euclidean distances from the camera centre."""


@dataclass
class Frame:
    """One photo: its file, camera-to-world pose (OpenGL axes) and pinhole intrinsics in pixels."""

    file_path: str
    c2w: np.ndarray
    """(4, 4) camera-to-world, OpenGL axes (camera looks down -Z, +Y up)."""
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    camera_model: str = "OPENCV"
    """The lens: OPENCV (radial-tangential k1 k2 p1 p2 k3; holds PINHOLE and the radial models) or
    OPENCV_FISHEYE (equidistant k1 k2 k3 k4). See `recon.capture.colmap.LENS_MODELS`."""
    split: str | None = None
    mask_path: str | None = None
    """Mask image of the photo (white = object; nerfstudio's `mask_path`): pixels outside are background. Stored
    like `file_path` (`Scene.mask_file`)."""
    near: float | None = None
    far: float | None = None
    """near/far: the ray segment to model, as a distance along unit-length rays (`RAY_DISTANCE`)."""
    time_s: float | None = None
    """For a video frame: its time stamp in the clip, seconds (the clip is in the file name)."""

    @property
    def name(self) -> str:
        return Path(self.file_path).name

    @property
    def stem(self) -> str:
        return Path(self.file_path).stem

    @property
    def distortion(self) -> tuple[float, ...]:
        """OpenCV's coefficient vector for this lens: (k1, k2, p1, p2, k3) or, for a fisheye, (k1, k2, k3, k4)."""
        if self.camera_model == "OPENCV_FISHEYE":
            return (self.k1, self.k2, self.k3, self.k4)
        return (self.k1, self.k2, self.p1, self.p2, self.k3)

    @property
    def center(self) -> np.ndarray:
        return self.c2w[:3, 3]

    def intrinsics_at(self, w: int, h: int) -> tuple[float, float, float, float]:
        """(fl_x, fl_y, cx, cy) in pixels of this photo resampled to w × h."""
        sx, sy = w / self.w, h / self.h
        return self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy


@dataclass
class Scene:
    """Cameras + sparse points + what normalize decided about the capture."""

    frames: list[Frame]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(P, 3) sparse points in the scene frame."""
    point_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.uint8))
    point_visibility: dict[str, np.ndarray] = field(default_factory=dict)
    """frame name → indices of the points that frame sees (for near/far)."""
    point_errors: np.ndarray | None = None
    """(P,) mean reprojection error of each point in pixels of the original photos (SfM); None: unknown."""
    aabb: np.ndarray | None = None
    """(2, 3) scene box [min, max] in the scene frame."""
    capture: str | None = None
    """'object' (cameras around, looking in) or 'unbounded' (forward-facing / wide scene)."""
    world_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    """(4, 4) similarity mapping the source (SfM or import) frame into this scene's frame."""
    region: np.ndarray | None = None
    """(2, 3) box of the object of interest (what the cameras look at; `recon.capture.region`), scene frame; None: all."""
    region_points: np.ndarray | None = None
    """(P,) bool: the sparse points normalize took for the object's (`Region.points`); None: not known (a scene from
    before they were kept, or no region), then the points inside `region` stand for them."""
    aside_points: np.ndarray | None = None
    """(P,) bool: the points normalize left out as things beside the object (`Region.aside`); None: not known."""
    ground: np.ndarray | None = None
    """(4,) plane (nx, ny, nz, d), n·x = d with unit n pointing up, of the ground the object stands on; None: none."""
    has_alpha: bool = False
    """Photos carry an alpha channel (known background, e.g. NeRF-synthetic RGBA)."""
    source_kind: str = "photos"
    notes: dict[str, Any] = field(default_factory=dict)
    root: Path | None = None
    """Folder that relative `file_path`s are resolved against (the scene folder for images recon wrote)."""
    source: Path | None = None
    """The input's folder as it is now: what a path starting `{source}/` (`SOURCE_MARK`) resolves against."""

    def observed_points(self, frame: Frame) -> np.ndarray | None:
        """(N, 3) the sparse points the frame's photo observes; None when the scene records none for it."""
        seen = self.point_visibility.get(frame.name)
        if seen is None:
            return None
        return np.asarray(self.points, np.float64).reshape(-1, 3)[np.asarray(seen, np.int64)]

    def image_path(self, frame: Frame) -> Path:
        return self.resolve(frame.file_path)

    def mask_file(self, frame: Frame) -> Path | None:
        """The frame's mask, resolved as `image_path` resolves photos: the masks recon wrote are relative to the scene
        folder (which works from any folder and wherever it is moved), the user's masks to the input's folder."""
        return self.resolve(frame.mask_path) if frame.mask_path else None

    def resolve(self, stored: str) -> Path:
        """A stored path as a file: `{source}/…` in the input's folder, another relative one in the scene folder."""
        if stored.startswith(SOURCE_MARK + "/"):
            if self.source is None:
                raise InputError(
                    f"The scene names its photos by their place in the input folder ({stored}), and which folder that "
                    f"is was not said. Run `recon run PHOTOS --out SCENE` with the photos folder."
                )
            return Path(os.path.normpath(self.source / stored[len(SOURCE_MARK) + 1:]))
        path = Path(stored)
        if path.is_absolute() or self.root is None:
            return path
        return self.root / path

    @property
    def source_from_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_from_source)

    def split(self, name: str) -> list[Frame]:
        return [f for f in self.frames if f.split == name]

    def to_json(self) -> dict:
        doc: dict[str, Any] = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "capture": self.capture,
            "source_kind": self.source_kind,
            "has_alpha": self.has_alpha,
            "aabb": None if self.aabb is None else np.asarray(self.aabb).tolist(),
            "region": None if self.region is None else np.asarray(self.region).tolist(),
            "ground": None if self.ground is None else np.asarray(self.ground).tolist(),
            "world_from_source": np.asarray(self.world_from_source).tolist(),
            "source_from_world": self.source_from_world.tolist(),
            "notes": self.notes,
            "frames": [],
        }
        shared = _shared_intrinsics(self.frames)
        doc.update(shared)
        for f in self.frames:
            entry: dict[str, Any] = {"file_path": f.file_path, "transform_matrix": np.asarray(f.c2w).tolist()}
            for key in INTRINSIC_KEYS:
                if key not in shared:
                    entry[key] = getattr(f, key)
            for key in ("split", "mask_path", "near", "far", "time_s"):
                if getattr(f, key) is not None:
                    entry[key] = getattr(f, key)
            doc["frames"].append(entry)
        return doc

    def save(self, folder: Path) -> None:
        """Write scene.json and points.npz into `folder` (atomically each)."""
        write_json_atomic(folder / "scene.json", self.to_json())
        vis_names = sorted(self.point_visibility)
        np.savez(
            folder / "points.npz",
            xyz=np.asarray(self.points, dtype=np.float64).reshape(-1, 3),
            rgb=np.asarray(self.point_colors, dtype=np.uint8).reshape(-1, 3),
            vis_names=np.array(vis_names, dtype=str),
            **{f"vis_{i}": np.asarray(self.point_visibility[n], dtype=np.int64) for i, n in enumerate(vis_names)},
            **({} if self.point_errors is None else {"error": np.asarray(self.point_errors, dtype=np.float64).reshape(-1)}),
            **{key: np.asarray(value, dtype=bool).reshape(-1) for key, value in
               (("region", self.region_points), ("aside", self.aside_points)) if value is not None},
        )


def _shared_intrinsics(frames: list[Frame]) -> dict[str, Any]:
    keys = INTRINSIC_KEYS
    if not frames:
        return {}
    first = {k: getattr(frames[0], k) for k in keys}
    if all(all(getattr(f, k) == first[k] for k in keys) for f in frames):
        return first
    return {}


def source_folder(source: Path) -> Path:
    """The folder of an input (photos, a clip, a poses file or model): what `{source}/` paths are relative to. One
    that is gone is taken for a file by its extension, so an error still names where its photos were looked for."""
    return source.parent if source.is_file() or (not source.exists() and source.suffix) else source


def stored_path(path: Path | str, source: Path) -> str:
    """How a scene stores a file of the input `source`: `{source}/…` when it lies in the input's folder or beside
    it (a `masks/` folder next to the photos), so the scene holds when the capture folder moves; else absolute."""
    folder = os.path.realpath(source_folder(Path(source)))
    where = os.path.realpath(path)
    relative = os.path.relpath(where, folder)
    if relative.startswith(os.pardir + os.sep + os.pardir) or os.path.isabs(relative):
        return where
    return f"{SOURCE_MARK}/{Path(relative).as_posix()}"


def load_scene(folder: Path, source: Path | None = None) -> Scene:
    """Read scene.json (+ points.npz) written by `Scene.save`; `source`: the input as it is now (a folder or file),
    which the photos stored as `{source}/…` are found in."""
    path = folder / "scene.json"
    try:
        doc = read_json(path)
    except (OSError, ValueError) as exc:
        raise InputError(f"Cannot read {path}: {exc}. Re-run the stage that writes it (recon run --from normalize).") from None
    if not isinstance(doc, dict) or doc.get("format") != SCENE_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(
            f"{path} is not a recon scene file (format '{found}'). Re-run the stage that writes it "
            f"(recon run --from normalize)."
        )
    frames = parse_frames(doc, base=folder, source=path, check_files=False)
    scene = Scene(
        frames=frames,
        aabb=None if doc.get("aabb") is None else _matrix(doc["aabb"], (2, 3), path, "aabb"),
        region=None if doc.get("region") is None else _matrix(doc["region"], (2, 3), path, "region"),
        ground=None if doc.get("ground") is None else _matrix(doc["ground"], (4,), path, "ground"),
        capture=doc.get("capture") if doc.get("capture") in (None, "object", "unbounded") else _bad(path, "capture"),
        world_from_source=_matrix(doc.get("world_from_source", np.eye(4).tolist()), (4, 4), path, "world_from_source"),
        has_alpha=bool(doc.get("has_alpha", False)),
        source_kind=doc.get("source_kind", "photos"),
        notes=doc.get("notes") if isinstance(doc.get("notes", {}), dict) and doc.get("notes") else {},
        root=folder.parent,
        source=None if source is None else source_folder(Path(source)),
    )
    points_path = folder / "points.npz"
    if points_path.exists():
        try:
            with np.load(points_path, allow_pickle=False) as data:
                scene.points = _matrix(data["xyz"], (len(data["xyz"]), 3), points_path, "xyz")
                scene.point_colors = data["rgb"]
                names = [str(n) for n in data["vis_names"]]
                scene.point_visibility = {n: data[f"vis_{i}"] for i, n in enumerate(names)}
                if "error" in data.files and len(data["error"]) == len(scene.points):
                    scene.point_errors = data["error"]
                if "region" in data.files and len(data["region"]) == len(scene.points):
                    scene.region_points = data["region"].astype(bool)
                if "aside" in data.files and len(data["aside"]) == len(scene.points):
                    scene.aside_points = data["aside"].astype(bool)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            raise InputError(f"Cannot read {points_path}: {exc}. Re-run the stage that writes it (recon run --from poses).") from None
    return scene


def _bad(path: Path, key: str) -> Any:
    raise InputError(f"{path}: '{key}' has an unexpected value. Re-run the stage that writes it (recon run --from normalize).")


# --------------------------------------------------------------------------------------------- parsing


def _matrix(value: Any, shape: tuple[int, ...], source: Path | str, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: '{what}' is not a numeric matrix. Fix or regenerate the file.") from None
    if arr.shape != shape:
        raise InputError(f"{source}: '{what}' has shape {arr.shape}, expected {shape}. Fix or regenerate the file.")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{source}: '{what}' contains NaN or infinite values. Fix or regenerate the file.")
    return arr


def check_pose(c2w: np.ndarray, source: Path | str, what: str) -> np.ndarray:
    """A camera-to-world must be a rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    R = c2w[:3, :3]
    if not np.allclose(c2w[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(f"{source}: {what} does not end in the row [0, 0, 0, 1]; it is not a camera pose.")
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-3 or np.linalg.det(R) < 0:
        raise InputError(
            f"{source}: {what} has a rotation that is not orthonormal (error {err:.2g}, det {np.linalg.det(R):.3f}). "
            f"Poses must be rigid camera-to-world matrices; scaled or sheared matrices are not supported."
        )
    # re-orthonormalize tiny float noise so downstream math sees an exact rotation
    u, _, vt = np.linalg.svd(R)
    out = c2w.copy()
    out[:3, :3] = u @ vt
    return out


def _number(value: Any, source: Path | str, what: str, positive: bool = False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{source}: '{what}' must be a number, got {value!r}.") from None
    if not math.isfinite(x) or (positive and x <= 0):
        raise InputError(f"{source}: '{what}' must be a finite{' positive' if positive else ''} number, got {value!r}.")
    return x


def resolve_image(base: Path, file_path: str, source: Path | str) -> Path:
    """Find a frame's image under `base`, allowing a missing extension (NeRF-synthetic writes './train/r_0')."""
    if not isinstance(file_path, str) or not file_path:
        raise InputError(f"{source}: a frame has no 'file_path'.")
    if "\x00" in file_path:
        raise InputError(f"{source}: the image path {file_path!r} contains a NUL character. Fix the file_path.")
    # lexical containment (no symlink resolution): '..' cannot escape, but a symlinked photo folder inside works
    root = Path(os.path.abspath(base))
    path = Path(os.path.normpath(root / file_path))
    if root not in path.parents:
        raise InputError(
            f"{source}: the image path '{file_path}' points outside the capture folder {root}. "
            f"Image paths must be relative and stay inside the folder that holds the poses file."
        )
    try:
        if path.is_file():
            return path
        for suffix in sorted(IMAGE_SUFFIXES) + [s.upper() for s in sorted(IMAGE_SUFFIXES)]:
            candidate = path.with_name(path.name + suffix)
            if candidate.is_file():
                return candidate
    except OSError as exc:  # e.g. a name too long for the file system
        raise InputError(f"{source}: the image path '{file_path}' cannot be used ({exc.strerror}). Fix the file_path.") from None
    raise InputError(f"{source}: the image '{file_path}' does not exist (looked for {path}). Fix the path or add the file.")


def parse_frames(
    doc: dict, base: Path, source: Path | str, check_files: bool = True, split: str | None = None
) -> list[Frame]:
    """Frames of a transforms.json-style document; intrinsics per frame or shared at the top level."""
    if not isinstance(doc, dict):
        raise InputError(f"{source}: expected a JSON object with a 'frames' list.")
    frames_doc = doc.get("frames")
    if not isinstance(frames_doc, list) or not frames_doc:
        raise InputError(f"{source}: no 'frames' list (or it is empty). A poses file needs one entry per photo.")
    frames = []
    for i, fd in enumerate(frames_doc):
        if not isinstance(fd, dict):
            raise InputError(f"{source}: frame {i} is not an object.")
        what = f"frame {i} ('{fd.get('file_path', '?')}')"
        if "transform_matrix" not in fd:
            raise InputError(f"{source}: {what} has no 'transform_matrix'.")
        c2w = check_pose(_matrix(fd["transform_matrix"], (4, 4), source, f"{what} transform_matrix"), source, what)
        if not isinstance(fd.get("file_path"), str) or not fd["file_path"] or "\x00" in fd["file_path"]:
            raise InputError(f"{source}: {what} has no usable 'file_path' (a relative path to its image).")
        path = resolve_image(base, fd["file_path"], source) if check_files else Path(fd["file_path"])
        merged = {**doc, **fd}
        if "w" in merged and "h" in merged:
            w, h = int(_number(merged["w"], source, "w", True)), int(_number(merged["h"], source, "h", True))
        elif check_files:
            w, h = oriented_size(path)
        else:
            raise InputError(f"{source}: {what} has no image size (w, h).")
        if "fl_x" in merged:
            fl_x = _number(merged["fl_x"], source, "fl_x", True)
            fl_y = _number(merged.get("fl_y", fl_x), source, "fl_y", True)
        elif "camera_angle_x" in merged:
            angle = _number(merged["camera_angle_x"], source, "camera_angle_x", True)
            if angle >= math.pi:
                raise InputError(f"{source}: camera_angle_x = {angle} rad is not a field of view below 180°.")
            fl_x = 0.5 * w / math.tan(0.5 * angle)
            fl_y = fl_x
            if "camera_angle_y" in merged:
                angle_y = _number(merged["camera_angle_y"], source, "camera_angle_y", True)
                if angle_y >= math.pi:
                    raise InputError(f"{source}: camera_angle_y = {angle_y} rad is not a field of view below 180°.")
                fl_y = 0.5 * h / math.tan(0.5 * angle_y)
        else:
            raise InputError(f"{source}: no focal length: give 'fl_x' (pixels) or 'camera_angle_x' (radians).")
        model = merged.get("camera_model", "OPENCV")
        if model not in LENS_MODELS:
            raise InputError(
                f"{source}: {what} has camera_model '{model}', which recon cannot undistort. Supported: "
                f"{', '.join(LENS_MODELS)}. Undistort the images to PINHOLE first (e.g. COLMAP's image_undistorter) "
                f"and set camera_model to PINHOLE."
            )
        lens = LENS_MODELS[model]
        coefficients = ("k1", "k2", "k3", "k4") if lens == "OPENCV_FISHEYE" else ("k1", "k2", "p1", "p2", "k3")
        frame = Frame(
            file_path=str(path),
            c2w=c2w,
            fl_x=fl_x,
            fl_y=fl_y,
            cx=_number(merged.get("cx", w / 2), source, "cx"),
            cy=_number(merged.get("cy", h / 2), source, "cy"),
            w=w,
            h=h,
            **{k: _number(merged.get(k, 0.0), source, k) for k in coefficients},
            camera_model=lens,
            split=fd.get("split", split),
            mask_path=_mask_path(base, fd, source, check_files),
            near=_number(fd["near"], source, "near", True) if "near" in fd else None,
            far=_number(fd["far"], source, "far", True) if "far" in fd else None,
            time_s=_number(fd["time_s"], source, "time_s") if "time_s" in fd else None,
        )
        if frame.split is not None and frame.split not in SPLITS:
            raise InputError(f"{source}: {what} has split '{frame.split}'; expected one of {', '.join(SPLITS)}.")
        frames.append(frame)
    return frames


def check_cameras(scene: Scene, source: Path | str) -> None:
    """Refuse cameras the later stages could not use, naming the input they came from (not recon's own files).

    Every pose and intrinsic must be finite, focal lengths positive with a field of view in (0°, 180°), the
    principal point inside the image, the image at least MIN_SIDE px a side, and the size the poses give must be
    the image's own (or the same picture scaled: equal aspect ratio, since views rescale intrinsics with the photo).
    """
    if not scene.frames:
        raise InputError(f"{source}: no cameras. A poses file (or COLMAP model) needs one camera per photo.")
    for f in scene.frames:
        what = f"{source}: the camera of {f.name}"
        values = np.array([*np.asarray(f.c2w, np.float64).ravel(), f.fl_x, f.fl_y, f.cx, f.cy, f.w, f.h, *f.distortion])
        if not np.all(np.isfinite(values)):
            raise InputError(f"{what} has NaN or infinite values (pose, focal, principal point or distortion). Fix the poses.")
        if not (f.fl_x > 0 and f.fl_y > 0):
            raise InputError(f"{what} has focal length ({f.fl_x:g}, {f.fl_y:g}) px; it must be positive. Fix the intrinsics.")
        fov = np.degrees(2 * np.arctan2([0.5 * f.w, 0.5 * f.h], [f.fl_x, f.fl_y]))
        if not np.all((fov > 0) & (fov < 180)):
            raise InputError(f"{what} has a field of view of {fov[0]:.4g}° × {fov[1]:.4g}°; it must be between 0° and 180°.")
        if min(f.w, f.h) < MIN_SIDE:
            raise InputError(f"{what} gives an image size of {f.w}×{f.h} px; recon needs at least {MIN_SIDE} px a side.")
        if not (0 <= f.cx <= f.w and 0 <= f.cy <= f.h):
            raise InputError(f"{what} has its principal point ({f.cx:g}, {f.cy:g}) outside the {f.w}×{f.h} image.")
        w, h = oriented_size(scene.image_path(f))
        if (w, h) != (f.w, f.h) and abs(w * f.h - h * f.w) > max(f.w, f.h):
            raise InputError(
                f"{what} says the image is {f.w}×{f.h} px but {scene.image_path(f)} is {w}×{h} px (another shape). "
                f"Fix w/h in the poses or use the images they were made for."
            )


def _mask_path(base: Path, fd: dict, source: Path | str, check_files: bool) -> str | None:
    if fd.get("mask_path") is None:
        return None
    if not check_files:
        return str(fd["mask_path"])
    return str(resolve_image(base, fd["mask_path"], source))


MASK_FOLDER = "masks"
UNSURE_MASK_FOLDER = "masks_unsure"
"""The scene folder's automatic masks that normalize was not sure enough of to train with: a start for the user's
masks, and what crops the mesh of the field trained without them (mesh.unsure_masks)."""


def pinhole_mask(path: Path, frame: Frame, w: int, h: int) -> np.ndarray:
    """A photo's mask (white = object, at the photo's pixels) at w × h with the photo's lens distortion removed, as
    bool: a pinhole image of the frame's camera, as the scene's cameras project."""
    return undistort(read_mask(path, (w, h)), *frame.intrinsics_at(w, h), frame.distortion, frame.camera_model) >= 0.5


def mask_homes(photos: Sequence[Path]) -> list[Path]:
    """Where a photos folder's masks folder may be: inside it, or next to it."""
    folder = photos[0].parent
    return [folder / MASK_FOLDER, folder.parent / MASK_FOLDER]


def video_mask_homes(source: Path) -> list[Path]:
    """Where a video's masks folder may be: next to the clip, or inside (or next to) a folder of clips. Its masks are
    named like the frames recon keeps (`recon.capture.video.frame_name`: the clip's name and the frame's index)."""
    if source.is_file():
        return [source.parent / MASK_FOLDER]
    return [source / MASK_FOLDER, source.parent / MASK_FOLDER]


def find_masks(photos: Sequence[Path], homes: Sequence[Path] | None = None) -> tuple[Path | None, dict[str, Path]]:
    """The masks folder (the first of `homes` that holds one, by default `mask_homes`) and each photo's mask (same
    stem, any image suffix; white = object). Raises InputError naming the photos a present folder lacks (`homes`
    given: the video frames recon kept)."""
    if not photos:
        return None, {}
    folder = photos[0].parent
    # a photos folder that is itself named masks/ is not its own masks folder
    candidates = mask_homes(photos) if homes is None else homes
    found = next((c for c in candidates if c.is_dir() and not c.samefile(folder)), None)
    if found is None:
        return None, {}
    by_stem = {p.stem: p for p in sorted(found.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES}
    if not by_stem:  # an empty folder: nothing to use
        return None, {}
    missing = [p.name for p in photos if p.stem not in by_stem]
    if missing and homes is not None:
        raise InputError(
            f"The masks folder {found} has no mask for {len(missing)} of the {len(photos)} video frames recon kept: "
            f"{', '.join(Path(m).stem + '.png' for m in missing[:5])}{'…' if len(missing) > 5 else ''}. A frame's "
            f"mask is named after the clip and the frame's index; a run without the masks folder writes its "
            f"automatic masks under these names (SCENE/02_scene/masks/) to start from. Give every kept frame a mask "
            f"(white = object), or move the masks folder away to run without masks."
        )
    if missing:
        raise InputError(
            f"The masks folder {found} has no mask for {len(missing)} photo(s): {', '.join(missing[:5])}"
            f"{'…' if len(missing) > 5 else ''}. Give every photo a mask with the same name (white = object), "
            f"or move the masks folder away to run without masks."
        )
    return found, {p.name: by_stem[p.stem] for p in photos}


# --------------------------------------------------------------------------------------------- imports


ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz", ".7z", ".rar")
"""Archives a capture may come in (from a phone's share sheet or a cloud drive): refused with how to unpack them."""


def check_source(path: Path) -> str:
    """`detect_source`, and for a folder of photos that it holds enough, named apart, for a video that its file is
    whole: what `recon run` tells of its input before it makes the scene folder and loads torch (a video is decoded
    by the poses stage alone: a cached run decodes none)."""
    kind = detect_source(path)
    if kind == "photos":
        photos, skipped = list_photos(path)
        if not photos:
            raise no_photos(path, skipped)
        check_photo_set(path, photos)
        check_photo_headers(path, photos)
    if kind == "video":
        from recon.capture.video import check_container, list_videos

        for clip in [path] if path.is_file() else list_videos(path):
            check_container(clip)
    return kind


def detect_source(path: Path) -> str:
    """What the user handed us: 'photos', 'video', 'transforms', 'nerf_synthetic', 'colmap' or 'npz'."""
    from recon.capture.video import is_video, list_videos

    if path.is_file() and path.suffix.lower() == ".npz":
        return "npz"
    if path.is_file() and is_video(path):
        return "video"
    if path.is_file() and path.name.endswith(".json"):
        return "transforms"
    if path.is_dir():
        if all((path / f"transforms_{s}.json").is_file() for s in ("train", "test")):
            return "nerf_synthetic"
        if (path / "transforms.json").is_file():
            return "transforms"
        if find_colmap_model(path) is not None:
            return "colmap"
        if list_videos(path):
            if any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir() if p.is_file()):
                raise InputError(
                    f"{path} holds both photos and videos. Put the videos in a folder of their own (recon takes "
                    f"frames from every video in a folder), or the photos, and pass that folder."
                )
            return "video"
        return "photos"
    if not path.exists():
        raise InputError(f"The input {path} does not exist. Pass a folder of photos (or a poses file).")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise InputError(
            f"The input {path} is one photo; recon needs many photos of the object, from all around it (20 or more). "
            f"Put them in a folder of their own and pass the folder: recon run {path.parent / 'photos'} --out SCENE."
        )
    if zipfile.is_zipfile(path) or path.name.lower().endswith(ARCHIVE_SUFFIXES):
        raise InputError(
            f"The input {path} is an archive; recon reads the photos themselves. Unpack it into a folder of its own "
            f"(for a zip: unzip {path} -d {path.parent / 'photos'}) and pass that folder."
        )
    raise InputError(
        f"The input {path} is a file recon cannot use. Pass a folder of photos, a video (MP4/MOV/M4V), a folder "
        f"with transforms.json, a COLMAP project/model folder, or a NeRF .npz file."
    )


def _load_json(path: Path) -> Any:
    try:
        return read_json(path)
    except OSError as exc:
        raise InputError(f"Cannot read {path}: {exc.strerror}.") from None
    except ValueError as exc:
        raise InputError(f"{path} cannot be used: {exc}. Fix or regenerate the file (is it really a poses file?).") from None


def import_transforms(path: Path) -> Scene:
    """instant-ngp / nerfstudio transforms.json (a file, or a folder holding one)."""
    json_path = path / "transforms.json" if path.is_dir() else path
    doc = _load_json(json_path)
    frames = parse_frames(doc, base=json_path.parent, source=json_path)
    masked = all(f.mask_path for f in frames)
    return Scene(frames=frames, has_alpha=masked or _has_alpha(frames[0]), source_kind="transforms")


def import_nerf_synthetic(folder: Path) -> Scene:
    """Blender NeRF-synthetic layout: transforms_{train,val,test}.json; its splits are kept."""
    frames: list[Frame] = []
    for split in SPLITS:
        json_path = folder / f"transforms_{split}.json"
        if not json_path.is_file():
            continue
        doc = _load_json(json_path)
        split_frames = parse_frames(doc, base=folder, source=json_path, split=split)
        frames += [f for f in split_frames if Path(f.file_path).is_file()]
    return Scene(frames=frames, has_alpha=_has_alpha(frames[0]), source_kind="nerf_synthetic")


def _has_alpha(frame: Frame) -> bool:
    from PIL import Image

    try:
        with Image.open(frame.file_path) as img:
            return img.mode in ("RGBA", "LA", "PA") or "transparency" in img.info
    except (OSError, ValueError) as exc:  # PIL's UnidentifiedImageError is an OSError
        raise InputError(
            f"Cannot read the image {frame.file_path}: {exc}. The file is corrupt or not an image; "
            f"fix the file_path or replace the file."
        ) from None


QUARTER_TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""The camera of a photo (OpenGL camera-to-world, right) against the camera of its copy turned a quarter
counterclockwise (`np.rot90`): the same centre, rolled about the optical axis."""


def turned_back(fd: dict) -> dict:
    """`recon.capture.sfm`'s per-image dict of a copy turned a quarter counterclockwise (`np.rot90`: pixel (x, y) of the
    copy is (h - y, x) of the photo, h the copy's height), made the photo's: the axes and focal lengths swapped, the
    principal point and the tangential distortion turned back (radial terms do not change with the roll)."""
    c2w = np.asarray(fd["c2w"], dtype=np.float64).copy()
    c2w[:3, :3] = c2w[:3, :3] @ QUARTER_TURN
    return {**fd, "c2w": c2w, "w": fd["h"], "h": fd["w"], "fl_x": fd["fl_y"], "fl_y": fd["fl_x"],
            "cx": fd["h"] - fd["cy"], "cy": fd["cx"], "p1": fd["p2"], "p2": -fd["p1"]}


def frame_from_sfm(file_path: str, fd: dict, sx: float = 1.0, sy: float = 1.0, turned: bool = False) -> Frame:
    """A Frame from `recon.capture.sfm`'s per-image dict, with intrinsics scaled by (sx, sy) to the photo's size;
    `turned`: SfM saw the photo turned a quarter counterclockwise (`turned_back`), (sx, sy) are of the photo upright."""
    if turned:
        fd = turned_back(fd)
    return Frame(
        file_path=file_path,
        c2w=np.asarray(fd["c2w"], dtype=np.float64),
        fl_x=fd["fl_x"] * sx,
        fl_y=fd["fl_y"] * sy,
        cx=fd["cx"] * sx,
        cy=fd["cy"] * sy,
        w=round(fd["w"] * sx),
        h=round(fd["h"] * sy),
        k1=fd["k1"],
        k2=fd["k2"],
        p1=fd["p1"],
        p2=fd["p2"],
        k3=fd.get("k3", 0.0),
        k4=fd.get("k4", 0.0),
        camera_model=fd.get("camera_model", "OPENCV"),
    )


def import_colmap(folder: Path, log_dir: Path | None = None) -> Scene:
    """A COLMAP sparse model (cameras/images/points3D .bin or .txt); images from the project's images/ folder.

    COLMAP's own log files go to `log_dir` (not /tmp)."""
    model, rec = read_model(folder, log_dir)
    names = sorted(rec.images[i].name for i in rec.images.keys())
    for root in (folder / "images", model / "images", model.parent / "images", model.parent.parent / "images", folder):
        if root.is_dir() and any((root / name).is_file() for name in names[:5]):
            try:
                fds, xyz, rgb, _, visible = reconstruction_frames(rec, names)
                frames = [frame_from_sfm(str(resolve_image(root, n, model)), fd) for n, fd in fds.items()]
            except ValueError as exc:
                cameras = next((p for p in (model / "cameras.bin", model / "cameras.txt") if p.is_file()), model)
                raise InputError(f"COLMAP model {cameras}: {exc}.") from None
            return Scene(
                frames=frames,
                points=xyz,
                point_colors=rgb,
                point_visibility={Path(n).name: v for n, v in visible.items()},
                source_kind="colmap",
            )
    raise InputError(
        f"Found the COLMAP model in {model} but not its images. Put them in {folder / 'images'} "
        f"(the usual COLMAP project layout)."
    )


def import_npz(path: Path, image_dir: Path) -> Scene:
    """The tiny-NeRF `.npz` (images (N,H,W,3) in [0,1] or uint8, poses (N,4,4) c2w OpenGL, focal): writes PNGs."""
    from recon.capture.images import save_image

    try:
        data = np.load(path, allow_pickle=False)
        images, poses, focal = data["images"], data["poses"], data["focal"]
    except KeyError as exc:
        raise InputError(f"{path}: missing array {exc}; a NeRF .npz needs 'images', 'poses' and 'focal'.") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"Cannot read {path}: {exc}. Is it a NumPy .npz file?") from None
    if images.dtype.kind not in "biuf" or poses.dtype.kind not in "biuf" or np.asarray(focal).dtype.kind not in "biuf":
        raise InputError(f"{path}: 'images', 'poses' and 'focal' must be numeric arrays. Fix or regenerate the file.")
    if images.ndim != 4 or images.shape[-1] not in (3, 4) or 0 in images.shape:
        raise InputError(f"{path}: 'images' has shape {images.shape}; expected (N, H, W, 3 or 4) with no images "
                         f"of zero size and N > 0 (the file holds no images otherwise).")
    if np.asarray(focal).size == 0:
        raise InputError(f"{path}: 'focal' is empty; it must hold the focal length in pixels.")
    n, h, w = images.shape[:3]
    if poses.shape not in ((n, 4, 4), (n, 3, 4)):
        raise InputError(f"{path}: 'poses' has shape {poses.shape}; expected ({n}, 4, 4) for the {n} images.")
    focal = _number(np.asarray(focal).reshape(-1)[0], path, "focal", True)
    # integers span their type (uint8 0-255, uint16 0-65535); floats must already be in [0, 1]
    scale = float(np.iinfo(images.dtype).max) if images.dtype.kind in "iu" else 1.0
    imgs = images.astype(np.float32) / scale
    if not np.all(np.isfinite(imgs)):
        raise InputError(f"{path}: 'images' contains NaN or infinite values.")
    if images.dtype.kind == "f" and (imgs.min() < -1e-3 or imgs.max() > 1 + 1e-3):
        raise InputError(f"{path}: float 'images' must be in [0, 1]; they span [{imgs.min():g}, {imgs.max():g}]. "
                         f"Divide them by 255 (or store them as uint8).")
    image_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        c2w = np.eye(4)
        c2w[: poses.shape[1], :] = _matrix(poses[i], poses.shape[1:], path, f"poses[{i}]")
        out = image_dir / f"{i:04d}.png"
        save_image(out, np.clip(imgs[i], 0, 1))
        frames.append(Frame(str(out), check_pose(c2w, path, f"poses[{i}]"), focal, focal, w / 2, h / 2, w, h))
    return Scene(frames=frames, has_alpha=images.shape[-1] == 4, source_kind="npz")


def spread_evenly(items: Sequence[Any], k: int) -> list[Any]:
    """At most k of items, evenly spaced over the sequence (first and last included)."""
    if k <= 0 or len(items) <= k:
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]
