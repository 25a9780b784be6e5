"""Exports other tools read: nerfstudio / instant-ngp `transforms.json`, a COLMAP text model, sparse points as PLY.

Cameras come from the scene folder in the frame asked for: `normalized` (recon's box, +Z up: the frame
the field and the default mesh live in) or `source` (the SfM or imported poses as they were, read from
`01_poses/`). Images are written undistorted beside the poses (copied byte for byte when they have no
distortion and no EXIF rotation), so every export describes plain pinhole cameras — what Gaussian-splatting
trainers and nerfstudio's `splatfacto` expect; a nerfstudio export's masks are undistorted with them into `masks/`.
(The mesh exporter is `recon.geometry.export`.)

An export folder follows recon's ownership rule (`recon.runner.ownership`): it is new, empty or an earlier export
(its `.recon-export.json` lists the files recon wrote); the export is built in a staging folder inside it and
moved in file by file, replacing only recon's own files, so whatever the user added there stays.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
from pathlib import Path
from typing import Any, Literal

import numpy as np

from recon.app.api import require_scene
from recon.atomic import write_json_atomic
from recon.camera import opengl_c2w_to_opencv_w2c
from recon.capture.images import HEIF_SUFFIXES
from recon.capture.scene import Frame, Scene, load_scene
from recon.errors import ReconError
from recon.runner.ownership import claim_folder, marker_name
from recon.runner.pipeline import recorded_source

ExportFormat = Literal["nerfstudio", "colmap", "points"]
ExportFrame = Literal["normalized", "source"]
FORMATS: tuple[str, ...] = ("nerfstudio", "colmap", "points")
FRAMES: tuple[str, ...] = ("normalized", "source")
MARKER = marker_name("export")
POINTS_FILE = "points.ply"


def scene_in_frame(scene_dir: Path, frame: ExportFrame) -> Scene:
    """The scene's cameras and sparse points in `frame`, with the normalized scene's split on every camera.

    `source` reads `01_poses/` (the poses exactly as SfM or the import gave them), restricted to and
    ordered like the cameras normalize kept; `normalized` reads `02_scene/`.
    """
    if frame not in FRAMES:
        raise ReconError(f"--frame must be one of {', '.join(FRAMES)}; got '{frame}'.")
    normalized_dir, source_dir = scene_dir / "02_scene", scene_dir / "01_poses"
    require_scene(scene_dir)
    has_normalized = (normalized_dir / "scene.json").is_file()
    if frame == "normalized" or has_normalized:
        if not has_normalized:
            raise ReconError(f"{scene_dir} has no normalized scene yet. Run `recon run PHOTOS --out {scene_dir} --until normalize` first.")
        normalized = load_scene(normalized_dir, recorded_source(scene_dir))
        if frame == "normalized":
            return normalized
    if not (source_dir / "scene.json").is_file():
        raise ReconError(f"{scene_dir} has no poses yet. Run `recon run PHOTOS --out {scene_dir} --until poses` first.")
    source = load_scene(source_dir, recorded_source(scene_dir))
    if not has_normalized:
        return source
    by_path = {f.file_path: f for f in source.frames}
    frames = []
    for f in normalized.frames:
        original = by_path.get(f.file_path)
        if original is None:
            raise ReconError(
                f"{normalized_dir / 'scene.json'} has a camera ({f.name}) that {source_dir / 'scene.json'} lacks: the stages are "
                f"out of step. Run `recon run PHOTOS --out {scene_dir} --until normalize` again."
            )
        frames.append(dataclasses.replace(original, split=f.split, near=None, far=None))
    return dataclasses.replace(source, frames=frames, root=source.root, notes={})


def export_scene(scene_dir: Path, fmt: ExportFormat, out: Path, frame: ExportFrame = "normalized", report: Any = None) -> list[Path]:
    """Write one export of the scene into `out` (new, empty or an earlier export: see `recon.runner.ownership`).

    Returns the main files written (for the user to open).
    """
    if fmt not in FORMATS:
        raise ReconError(f"--format must be one of {', '.join(FORMATS)}; got '{fmt}'.")
    scene = scene_in_frame(scene_dir, frame)
    owned = claim_folder(out, "export", _scene_parts)
    with owned.staging() as tmp:
        if fmt == "points":
            written = [write_points_ply(scene, tmp / POINTS_FILE)]
        else:
            names = export_names(scene)
            frames = write_undistorted_images(scene, tmp / "images", names, report)
            if fmt == "nerfstudio":
                masks = write_undistorted_masks(scene, tmp, names)
                written = [write_transforms(scene, frames, names, masks, tmp, frame)]
            else:
                written = write_colmap_text(scene, frames, names, tmp / "sparse" / "0")
        owned.record = {"format": fmt, "frame": frame, "scene": str(scene_dir.resolve()), "cameras": len(scene.frames)}
        owned.replace_with(tmp)
    return [out / p.relative_to(tmp) for p in written]


def _scene_parts() -> frozenset[str]:
    """`recon.stages.scene_parts`, loaded only when --out lies inside a scene: the stages load torch (~7 s cold),
    which an export otherwise never needs."""
    from recon.stages import scene_parts

    return scene_parts()


def export_names(scene: Scene) -> list[str]:
    """Each camera's image path inside the export: relative to the photos' common folder (unique, e.g. 'train/r_0.png')."""
    paths = [os.path.abspath(scene.image_path(f)) for f in scene.frames]
    root = os.path.commonpath([os.path.dirname(p) for p in paths])
    names = [Path(os.path.relpath(p, root)).as_posix() for p in paths]
    # HEIC goes out as JPEG: the tools an export is for (nerfstudio, COLMAP, 3DGS) do not read it
    names = [str(Path(n).with_suffix(".jpg")) if Path(n).suffix.lower() in HEIF_SUFFIXES else n for n in names]
    if len(set(names)) != len(names):  # the same photo twice: keep them apart by position
        names = [f"{i:04d}_{Path(n).name}" for i, n in enumerate(names)]
    return names


def write_undistorted_images(scene: Scene, folder: Path, names: list[str], report: Any = None) -> list[Frame]:
    """Each camera's photo at full size without lens distortion; returns the frames with zero distortion.

    A photo with no distortion and no EXIF rotation is copied byte for byte; any other is decoded
    (rotation applied), undistorted with the same pinhole intrinsics and re-encoded.
    """
    from PIL import Image

    from recon.capture.images import read_image, save_image, undistort

    out_frames = []
    with report.task("writing undistorted images", total=len(scene.frames)) if report else contextlib.nullcontext() as bar:
        for frame, name in zip(scene.frames, names, strict=True):
            src = scene.image_path(frame)
            dst = folder / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            try:
                with Image.open(src) as img:
                    rotated = img.getexif().get(0x0112, 1) != 1
            except OSError as exc:
                raise ReconError(f"Cannot read the photo {src} ({exc}); it was readable when the scene was made. Restore it and export again.") from None
            same_format = Path(src).suffix.lower() == dst.suffix.lower()
            if not any(frame.distortion) and frame.camera_model != "OPENCV_FISHEYE" and not rotated and same_format:
                shutil.copyfile(src, dst)
            else:
                image = read_image(src)
                if image.shape[:2] != (frame.h, frame.w):
                    raise ReconError(f"The photo {src} is {image.shape[1]}×{image.shape[0]} but its camera says {frame.w}×{frame.h}: "
                                     f"it changed since the scene was made. Re-run `recon run` first.")
                image = undistort(image, frame.fl_x, frame.fl_y, frame.cx, frame.cy, frame.distortion, frame.camera_model)
                save_image(dst, image if dst.suffix.lower() == ".png" else image[..., :3])
            out_frames.append(dataclasses.replace(frame, file_path=str(dst), k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0,
                                                  camera_model="OPENCV"))
            if bar:
                bar.advance()
    return out_frames


MASKS_FOLDER = "masks"


def write_undistorted_masks(scene: Scene, folder: Path, names: list[str]) -> list[str | None]:
    """Each camera's mask as an 8-bit PNG (white = object) at its photo's size, undistorted like the photo, under
    `folder/masks/`; returns each mask's path relative to `folder` (None for a camera without one).

    The masks the scene points to live in the photos' lens space (and recon's automatic ones at their own size, in
    the scene folder): the exported images are undistorted, so the masks must be too, and inside the export.
    """
    from recon.capture.images import read_mask, save_image, undistort

    written: list[str | None] = []
    for frame, name in zip(scene.frames, names, strict=True):
        src = scene.mask_file(frame)
        if src is None:
            written.append(None)
            continue
        try:
            mask = read_mask(src, (frame.w, frame.h))
        except ReconError as exc:
            raise ReconError(f"{exc} The scene's camera {frame.name} names this mask; restore it and export again.") from None
        mask = undistort(mask, frame.fl_x, frame.fl_y, frame.cx, frame.cy, frame.distortion, frame.camera_model)
        rel = Path(MASKS_FOLDER) / Path(name).with_suffix(".png")
        if rel.as_posix() in written:  # photos a.jpg and a.png side by side
            rel = Path(MASKS_FOLDER) / f"{name}.png"
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        save_image(folder / rel, mask)
        written.append(rel.as_posix())
    return written


def write_transforms(scene: Scene, frames: list[Frame], names: list[str], masks: list[str | None], folder: Path,
                     frame_name: str) -> Path:
    """transforms.json (nerfstudio / instant-ngp: OpenGL c2w, OPENCV intrinsics with zero distortion) + sparse points.

    Splits go in nerfstudio's `train_filenames` / `val_filenames` / `test_filenames` and per frame
    (`split`, which recon reads back); masks in `mask_path`, relative like the images; the sparse points in
    `ply_file_path` (splatfacto's initialisation).
    """
    doc = Scene(frames=[dataclasses.replace(f, file_path=f"images/{n}", mask_path=m)
                        for f, n, m in zip(frames, names, masks, strict=True)],
                aabb=scene.aabb, capture=scene.capture, world_from_source=scene.world_from_source).to_json()
    for key in ("format", "version", "source_kind", "has_alpha", "notes"):
        doc.pop(key, None)
    doc["recon_frame"] = frame_name
    for split in ("train", "val", "test"):
        chosen = [f"images/{n}" for f, n in zip(frames, names, strict=True) if f.split == split]
        if chosen:
            doc[f"{split}_filenames"] = chosen
    if len(scene.points):
        write_points_ply(scene, folder / POINTS_FILE)
        doc["ply_file_path"] = POINTS_FILE
    path = folder / "transforms.json"
    write_json_atomic(path, doc)
    return path


def write_colmap_text(scene: Scene, frames: list[Frame], names: list[str], folder: Path) -> list[Path]:
    """A COLMAP text model (cameras.txt, images.txt, points3D.txt, via pycolmap) of PINHOLE cameras.

    Poses are world-to-camera in OpenCV axes, as COLMAP stores them; the sparse points keep their
    colours but no tracks (recon keeps which photos see a point, not where).
    """
    import pycolmap

    folder.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for i, (frame, name) in enumerate(zip(frames, names, strict=True), start=1):
        key = (frame.w, frame.h, frame.fl_x, frame.fl_y, frame.cx, frame.cy)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            camera = pycolmap.Camera(model="PINHOLE", width=frame.w, height=frame.h,
                                     params=[frame.fl_x, frame.fl_y, frame.cx, frame.cy], camera_id=camera_ids[key])
            rec.add_camera_with_trivial_rig(camera)
        w2c = opengl_c2w_to_opencv_w2c(frame.c2w)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=i), pose)
    colors = np.asarray(scene.point_colors, np.uint8).reshape(-1, 3)
    for xyz, rgb in zip(np.asarray(scene.points, np.float64).reshape(-1, 3), colors, strict=True):
        rec.add_point3D(xyz, pycolmap.Track(), rgb)
    rec.write_text(str(folder))
    return [folder / "cameras.txt", folder / "images.txt", folder / "points3D.txt"]


def write_points_ply(scene: Scene, path: Path) -> Path:
    """The sparse SfM points with their colours as a PLY point cloud (binary, float32 xyz, uchar rgb)."""
    import trimesh

    if not len(scene.points):
        raise ReconError(
            "The scene has no sparse points (its poses were imported without any). The points export needs an SfM "
            "reconstruction: run recon on the photos themselves, or import a COLMAP model."
        )
    colors = np.asarray(scene.point_colors, np.uint8).reshape(-1, 3)
    trimesh.PointCloud(np.asarray(scene.points, np.float64), colors=colors).export(path)
    return path
