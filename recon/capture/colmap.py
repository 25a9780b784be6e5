"""COLMAP sparse models in recon's conventions: finding and reading a model, and converting its cameras and points.

Both ways a COLMAP model reaches recon go through here: structure from motion (`recon.capture.sfm` runs COLMAP and
converts the model it chose) and importing a model someone made (`recon.capture.scene.import_colmap`).

- poses: COLMAP gives world->camera in OpenCV axes (camera looks down +Z, +Y down); recon's frames are
  camera-to-world 4x4 matrices in the OpenGL convention (camera looks down -Z, +Y up, +X right), still in
  COLMAP's world frame;
- intrinsics: fl_x, fl_y, cx, cy (pixels) and the OpenCV-style distortion k1, k2, p1, p2 (k3, k4 for a
  fisheye) of the transforms.json convention.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from recon.camera import opencv_w2c_to_opengl_c2w
from recon.errors import InputError

if TYPE_CHECKING:  # pycolmap is imported when a model is read: loading options (recon.config) must not pay for it
    import pycolmap

LENS_MODELS = {
    "SIMPLE_PINHOLE": "OPENCV", "PINHOLE": "OPENCV", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV",
    "OPENCV": "OPENCV", "OPENCV_FISHEYE": "OPENCV_FISHEYE",
}
"""transforms.json / COLMAP camera_model -> the lens recon undistorts it as. Pinhole and radial models are
radial-tangential with some terms zero; a fisheye is OpenCV's equidistant model (k1..k4)."""


def camera_params_to_intrinsics(model_name: str, params: np.ndarray) -> dict[str, float]:
    """COLMAP camera params -> {"fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4"} (pixels; unitless k, p).

    Supports the models whose distortion the transforms.json convention can hold:
    SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx, fy, cx, cy), SIMPLE_RADIAL (f, cx, cy, k),
    RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2, p1, p2) and
    OPENCV_FISHEYE (fx, fy, cx, cy, k1, k2, k3, k4; see `LENS_MODELS`).
    """
    p = [float(v) for v in params]
    layouts: dict[str, tuple[str, ...]] = {
        "SIMPLE_PINHOLE": ("f", "cx", "cy"),
        "PINHOLE": ("fl_x", "fl_y", "cx", "cy"),
        "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
        "RADIAL": ("f", "cx", "cy", "k1", "k2"),
        "OPENCV": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"),
        "OPENCV_FISHEYE": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"),
    }
    if model_name not in layouts:
        raise ValueError(
            f"camera model {model_name} is not supported; use one of {', '.join(LENS_MODELS)} "
            "(or undistort the images to PINHOLE with COLMAP's image_undistorter first)"
        )
    names = layouts[model_name]
    if len(p) != len(names):
        raise ValueError(f"{model_name} takes {len(names)} params, got {len(p)}")
    values = dict(zip(names, p))
    if "f" in values:
        values["fl_x"] = values["fl_y"] = values.pop("f")
    out = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0, "k4": 0.0}
    out.update(values)
    return {k: out[k] for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4")}


def reconstruction_frames(
    rec: pycolmap.Reconstruction, names: list[str]
) -> tuple[dict[str, dict], np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Frames (OpenGL c2w + intrinsics) and sparse points of a reconstruction."""
    frames: dict[str, dict] = {}
    image_name_by_id: dict[int, str] = {}
    for image_id, image in rec.images.items():
        if not image.has_pose:
            continue
        camera = rec.cameras[image.camera_id]
        c2w = opencv_w2c_to_opengl_c2w(image.cam_from_world().matrix())
        frame: dict = {"c2w": c2w.tolist()}
        frame.update(camera_params_to_intrinsics(camera.model_name, camera.params))
        frame["camera_model"] = LENS_MODELS[camera.model_name]
        frame["w"], frame["h"] = int(camera.width), int(camera.height)
        frames[image.name] = frame
        image_name_by_id[image_id] = image.name
    point_ids = sorted(rec.points3D.keys())
    num = len(point_ids)
    xyz = np.zeros((num, 3), dtype=np.float64)
    rgb = np.zeros((num, 3), dtype=np.uint8)
    err = np.zeros((num,), dtype=np.float64)
    seen: dict[str, list[int]] = {name: [] for name in frames}
    for index, point_id in enumerate(point_ids):
        point = rec.points3D[point_id]
        xyz[index] = point.xyz
        rgb[index] = point.color
        err[index] = point.error
        for image_id in {el.image_id for el in point.track.elements}:
            name = image_name_by_id.get(image_id)
            if name is not None:
                seen[name].append(index)
    visible = {name: np.asarray(idx, dtype=np.int64) for name, idx in seen.items()}
    ordered = {name: frames[name] for name in names if name in frames}
    return ordered, xyz, rgb, err, visible


def find_colmap_model(path: Path) -> Path | None:
    """A COLMAP sparse model folder: `path` itself, `path/sparse/0`, or `path/sparse`."""
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "colmap" / "sparse" / "0"):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    return None


_COLMAP_MIN_RECORD = {"cameras.bin": 24, "images.bin": 73, "points3D.bin": 51, "rigs.bin": 8, "frames.bin": 8}
"""Fewest bytes one record of each COLMAP binary file takes (its fixed fields; variable parts count as empty)."""


def check_colmap_binaries(model: Path) -> None:
    """Refuse COLMAP .bin files whose header promises more records than the file can hold.

    COLMAP reserves memory for the count in the first 8 bytes: a truncated or foreign file (a 4-byte
    points3D.bin) made pycolmap allocate without bound. This reads only the headers and sizes."""
    for name, min_record in _COLMAP_MIN_RECORD.items():
        path = model / name
        if not path.is_file():
            continue
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
        count = struct.unpack("<Q", head)[0] if len(head) == 8 else None
        if count is None or count * min_record > size - 8:
            found = "shorter than its 8-byte header" if count is None else f"says it holds {count:,} records"
            raise InputError(
                f"The COLMAP file {path} is damaged: it is {size:,} bytes and {found}. Re-export the model from "
                f"COLMAP (File > Export model), or pass the photos folder to run structure from motion again."
            )


def pycolmap_logging_to(log_dir: Path | None) -> None:
    """Send COLMAP's own log files (glog: `colmap.ERROR.<date>.<pid>` ...) into `log_dir` instead of /tmp."""
    import pycolmap

    if log_dir is None:
        return
    log_dir.mkdir(parents=True, exist_ok=True)
    for level in (pycolmap.logging.Level.INFO, pycolmap.logging.Level.WARNING, pycolmap.logging.Level.ERROR):
        pycolmap.logging.set_log_destination(level, str(log_dir / f"colmap.{level.name}."))


def read_model(folder: Path, log_dir: Path | None = None) -> tuple[Path, pycolmap.Reconstruction]:
    """The COLMAP sparse model in `folder` (see `find_colmap_model`) and where it was, its binaries checked first;
    COLMAP's own log files go to `log_dir` (not /tmp)."""
    import pycolmap

    pycolmap_logging_to(log_dir)
    model = find_colmap_model(folder)
    if model is None:
        raise InputError(f"{folder} holds no COLMAP model (cameras.bin / cameras.txt).")
    check_colmap_binaries(model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on damaged files
        raise InputError(f"Cannot read the COLMAP model in {model}: {exc}. Re-export it from COLMAP.") from None
    return model, rec
