"""Bad and hostile input: each gives one clear paragraph naming the file and the fix, a non-zero exit, no traceback.

Malformed transforms.json / scene.json / .npz imports, out-of-range options, files that cannot be
read (a folder or a FIFO where a file belongs, a dangling link), unicode and spaces in paths, a
symlinked photo folder (which must work), and a hypothesis fuzz of the importers: they return a
valid Scene or raise InputError, never anything else.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import shutil
import struct
import sys
import typing
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image
from typer.testing import CliRunner

from recon.app.cli import app
from recon.camera import look_at
from recon.capture.images import read_image
from recon.capture.scene import Scene, import_npz, import_transforms, load_scene
from recon.config import (
    BOUNDS,
    TEXTURE_BAKE_BYTES_PER_TEXEL,
    RunConfig,
    available_presets,
    load_config,
    machine_memory_bytes,
)
from recon.errors import ConfigError, InputError
from recon.runner.pipeline import MANIFEST_VERSION

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "fixtures" / "sample"
runner = CliRunner()


def recon(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.output


def assert_clean_error(code: int, output: str, *needles: str) -> None:
    """Exit 2 (a user error), no traceback, and every needle (the file, the fix) in the message."""
    assert code == 2, output
    assert "Traceback" not in output and "internal error" not in output, output
    flat = " ".join(output.split())
    for needle in needles:
        assert needle in flat, output


def _rgb(path: Path, size: int = 32, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (size, size, 3), dtype=np.uint8)).save(path)


def _pose(angle: float) -> list[list[float]]:
    """A camera 3 units from the origin on a circle, looking at it (OpenGL c2w)."""
    eye = np.array([3 * math.cos(angle), 3 * math.sin(angle), 0.5])
    return look_at(eye, np.zeros(3)).tolist()


def _capture(folder: Path, n: int = 4) -> dict:
    """A small transforms.json capture (images/ + transforms.json); returns the document written."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        _rgb(folder / "images" / f"v{i}.png", seed=i)
        frames.append({"file_path": f"images/v{i}.png", "transform_matrix": _pose(2 * math.pi * i / n)})
    doc = {"fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 16.0, "w": 32, "h": 32, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(doc))
    return doc


def _write_doc(folder: Path, doc: dict) -> None:
    (folder / "transforms.json").write_text(json.dumps(doc))


def _run_import(folder: Path, out: Path) -> tuple[int, str]:
    return recon("run", str(folder), "--out", str(out), "--until", "normalize", "-q")


def _mutate(doc: dict, key: str) -> dict:
    bad = copy.deepcopy(doc)
    frame = bad["frames"][1]
    if key == "no-frames":
        del bad["frames"]
    elif key == "no-matrix":
        del frame["transform_matrix"]
    elif key == "nan":
        frame["transform_matrix"][0][3] = float("nan")
    elif key == "inf":
        frame["transform_matrix"][1][1] = float("inf")
    elif key == "scaled":
        frame["transform_matrix"] = (np.asarray(frame["transform_matrix"]) * np.diag([2, 2, 2, 1])).tolist()
    elif key == "shape":
        frame["transform_matrix"] = frame["transform_matrix"][:3]
    elif key == "escape":
        frame["file_path"] = "../../etc/passwd"
    elif key == "absolute-escape":
        frame["file_path"] = "/etc/passwd"
    elif key == "no-focal":
        del bad["fl_x"], bad["fl_y"]
    elif key == "negative-focal":
        bad["fl_x"] = -5
    elif key == "string-matrix":
        frame["transform_matrix"] = "identity"
    elif key == "missing-image":
        frame["file_path"] = "images/nope.png"
    elif key == "bad-split":
        frame["split"] = "holdout"
    return bad


# (mutation, words the message must contain besides the file's name)
TRANSFORMS_CASES = [
    ("no-frames", "'frames'"),
    ("no-matrix", "transform_matrix"),
    ("nan", "NaN or infinite"),
    ("inf", "NaN or infinite"),
    ("scaled", "not orthonormal"),
    ("shape", "shape (3, 4), expected (4, 4)"),
    ("escape", "outside the capture folder"),
    ("absolute-escape", "outside the capture folder"),
    ("no-focal", "fl_x"),
    ("negative-focal", "fl_x"),
    ("string-matrix", "not a numeric matrix"),
    ("missing-image", "does not exist"),
    ("bad-split", "holdout"),
]


@pytest.mark.parametrize(("mutation", "needle"), TRANSFORMS_CASES, ids=[c[0] for c in TRANSFORMS_CASES])
def test_malformed_transforms_json(tmp_path: Path, mutation: str, needle: str) -> None:
    cap = tmp_path / "cap"
    doc = _capture(cap)
    _write_doc(cap, _mutate(doc, mutation))
    assert_clean_error(*_run_import(cap, tmp_path / "scene"), "transforms.json", needle)


def test_transforms_json_that_is_not_json_or_not_an_object(tmp_path: Path) -> None:
    cap = tmp_path / "cap"
    _capture(cap)
    (cap / "transforms.json").write_text('{"frames": [')
    assert_clean_error(*_run_import(cap, tmp_path / "s1"), "transforms.json", "not valid JSON")
    (cap / "transforms.json").write_text("[1, 2, 3]")
    assert_clean_error(*_run_import(cap, tmp_path / "s2"), "transforms.json", "JSON object")
    (cap / "transforms.json").write_bytes(b"\xff\xfe\x00garbage")
    assert_clean_error(*_run_import(cap, tmp_path / "s3"), "transforms.json", "UTF-8")


def test_image_path_that_is_not_an_image(tmp_path: Path) -> None:
    """A frame pointing at a text file inside the capture: named, not an internal error."""
    cap = tmp_path / "cap"
    doc = _capture(cap)
    (cap / "images" / "notes.png").write_text("not a picture")
    doc["frames"][0]["file_path"] = "images/notes.png"
    _write_doc(cap, doc)
    assert_clean_error(*_run_import(cap, tmp_path / "scene"), "notes.png")


def test_folder_fifo_and_dangling_link_where_an_image_belongs(tmp_path: Path) -> None:
    cap = tmp_path / "cap"
    doc = _capture(cap)
    for i, make in enumerate(
        [lambda p: p.mkdir(), lambda p: os.mkfifo(p), lambda p: p.symlink_to(tmp_path / "gone.png")]
    ):
        target = cap / "images" / f"v{i}.png"
        target.unlink()
        make(target)
        code, out = _run_import(cap, tmp_path / f"scene{i}")
        assert_clean_error(code, out, f"v{i}.png", "does not exist")
        target.unlink() if not target.is_dir() or target.is_symlink() else target.rmdir()
        _rgb(target, seed=i)
    _write_doc(cap, doc)
    assert _run_import(cap, tmp_path / "ok")[0] == 0


def test_a_folder_where_the_poses_file_belongs(tmp_path: Path) -> None:
    (tmp_path / "poses.json").mkdir()
    code, out = recon("run", str(tmp_path / "poses.json"), "--out", str(tmp_path / "s"))
    assert_clean_error(code, out, "No photos found")


def test_hostile_scene_json(tmp_path: Path) -> None:
    folder = tmp_path / "02_scene"
    folder.mkdir()
    cases = {
        "[]": "not a recon scene file",
        '{"format": "recon-scene", "frames": "many"}': "'frames'",
        '{"format": "recon-scene", "aabb": [[0, 0], [1, 1]], "frames": [{"file_path": "a.png", '
        '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "fl_x": 10, "w": 8, "h": 8}]}': "'aabb'",
        '{"format": "other"}': "not a recon scene file",
        "\x00\x01": "Cannot read",
    }
    for text, needle in cases.items():
        (folder / "scene.json").write_text(text)
        with pytest.raises(InputError, match=needle) as info:
            load_scene(folder)
        assert "scene.json" in str(info.value)


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def _good_npz() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "images": rng.random((3, 24, 24, 3)).astype(np.float32),
        "poses": np.stack([np.asarray(_pose(a)) for a in (0.0, 2.0, 4.0)]).astype(np.float32),
        "focal": np.array(20.0),
    }


NPZ_CASES = {
    "missing-focal": (lambda d: d.pop("focal"), "focal"),
    "nan-pose": (lambda d: d["poses"].__setitem__((1, 0, 3), np.nan), "NaN"),
    "sheared-pose": (lambda d: d["poses"].__setitem__((1, 0, 1), 0.7), "not orthonormal"),
    "pose-shape": (lambda d: d.__setitem__("poses", d["poses"][:2]), "poses"),
    "image-shape": (lambda d: d.__setitem__("images", d["images"][..., 0]), "images"),
    "no-images": (lambda d: d.__setitem__("images", d["images"][:0]) or d.__setitem__("poses", d["poses"][:0]), "no images"),
    "string-images": (lambda d: d.__setitem__("images", np.full((3, 24, 24, 3), "x")), "images"),
    "empty-focal": (lambda d: d.__setitem__("focal", np.zeros(0)), "focal"),
    "zero-focal": (lambda d: d.__setitem__("focal", np.array(0.0)), "focal"),
}


@pytest.mark.parametrize("case", list(NPZ_CASES))
def test_malformed_npz(tmp_path: Path, case: str) -> None:
    data = _good_npz()
    mutate, needle = NPZ_CASES[case]
    mutate(data)
    path = _npz(tmp_path / "tiny nerf.npz", **data)
    code, out = recon("run", str(path), "--out", str(tmp_path / "scene"), "--until", "poses", "-q")
    assert_clean_error(code, out, "tiny nerf.npz", needle)


def test_npz_that_is_not_an_npz(tmp_path: Path) -> None:
    for i, payload in enumerate([b"hello", b"PK\x03\x04 broken zip", b""]):
        path = tmp_path / f"bad{i}.npz"
        path.write_bytes(payload)
        code, out = recon("run", str(path), "--out", str(tmp_path / f"s{i}"), "--until", "poses", "-q")
        assert_clean_error(code, out, f"bad{i}.npz")


# ------------------------------------------------------------------------------------------------ config

CONFIG_CASES = [
    ("train.steps=-5", "train.steps", "at least 1"),
    ("train.batch_rays=0", "train.batch_rays", "at least 1"),
    ("mesh.resolution=-3", "mesh.resolution", "at least 8"),
    ("mesh.min_component_fraction=2", "mesh.min_component_fraction", "at most 1"),
    ("train.lr=-1e-3", "train.lr", "at least 0"),
    ("train.steps=many", "train.steps", "expects a number"),
    ("train.steps=2.5", "train.steps", "whole number"),
    ("train.lr=nan", "train.lr", "expects a number"),
    ("train.bogus=1", "train.bogus", "Valid keys"),
    ("nosection.x=1", "nosection.x", "Valid keys"),
    ("train.fast=3", "train.fast", "not a value"),
    ("mesh.color=rainbow", "mesh.color", "must be one of"),
    ("train.steps", "train.steps", "KEY=VALUE"),
]


@pytest.mark.parametrize(("override", "key", "needle"), CONFIG_CASES, ids=[c[0] for c in CONFIG_CASES])
def test_invalid_option_values(tmp_path: Path, override: str, key: str, needle: str) -> None:
    cap = tmp_path / "cap"
    _capture(cap)
    code, out = recon("run", str(cap), "--out", str(tmp_path / "scene"), "--set", override)
    assert_clean_error(code, out, key, needle)
    assert not (tmp_path / "scene" / "01_poses").exists()  # refused before any work


def test_unknown_and_broken_presets(tmp_path: Path) -> None:
    cap = tmp_path / "cap"
    _capture(cap)
    out = str(tmp_path / "scene")
    assert_clean_error(*recon("run", str(cap), "--out", out, "--preset", "nonexistent"), "Unknown preset", "nonexistent")
    bad = tmp_path / "mine.toml"
    bad.write_text("[train]\nsteps = -1\n")
    assert_clean_error(*recon("run", str(cap), "--out", out, "--preset", str(bad)), "train.steps", "at least 1")
    bad.write_text("[train\nsteps = 1\n")
    assert_clean_error(*recon("run", str(cap), "--out", out, "--preset", str(bad)), "mine.toml", "not valid TOML")
    bad.write_text("[trian]\nsteps = 1\n")
    assert_clean_error(*recon("run", str(cap), "--out", out, "--preset", str(bad)), "[trian]", "Valid sections")


def numeric_options(config: object, prefix: str = "") -> list[str]:
    """Dotted names of every int and float option of a config (nested sections included)."""
    hints = typing.get_type_hints(type(config))
    names: list[str] = []
    for f in dataclasses.fields(config):  # type: ignore[arg-type]
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            names += numeric_options(value, f"{prefix}{f.name}.")
        elif hints[f.name] in (int, float):
            names.append(f"{prefix}{f.name}")
    return names


def test_every_numeric_option_has_bounds_and_defaults_and_presets_pass() -> None:
    assert sorted(BOUNDS) == sorted(numeric_options(RunConfig()))
    config = RunConfig()
    for dotted, bound in BOUNDS.items():
        value = config
        for part in dotted.split("."):
            value = getattr(value, part)
        assert bound.ok(value), f"the default {dotted}={value} is outside its own bounds"
    for preset in available_presets():
        load_config(preset)  # raises if a shipped preset broke its bounds
    with pytest.raises(ConfigError, match="train.steps"):
        load_config(None, ["train.steps=0"])


CROSS_CASES = [
    (["train.batch_rays=262144", "train.depth_rays=512"], "rays per training step"),
    (["normalize.test_every=2", "normalize.val_every=2"], "none would be left to train on"),
    (["mesh.resolution=4096", "mesh.memory_budget_mb=1073741824"], "more than this machine"),
    (["train.fast.density_res=1024", "train.fast.feature_res=1024", "train.fast.feature_dim=64"], "more than this machine"),
    (["mesh.texture_size=8192"], None),
    (["train.fast.occupancy_every=0"], "train.fast.occupancy_every"),
    (["train.fast.init_alpha=1"], "below 1"),
    (["train.fast.sh_degree=4"], "at most 3"),
    (["train.fast.distortion_weight=0.03", "train.fast.distortion_from=0.5", "train.fast.distortion_until=0.4"],
     "no share of training"),
    (["train.fast.distortion_until=0"], "greater than 0"),
    (["train.surface.eikonal_samples=0"], "at least 1"),
    (["mesh.texture_faces=300000"], "at most 150000"),
    (["train.fast.aabb=[[0, 0, 0], [0, 1, 1]]"], "each min below its max"),
]


@pytest.mark.parametrize(("overrides", "needle"), CROSS_CASES, ids=[" ".join(c[0]) for c in CROSS_CASES])
def test_cross_key_and_memory_checks(overrides: list[str], needle: str | None) -> None:
    """Several options at once, and the memory they imply against this machine's, refused before any stage."""
    if needle is None:  # the largest texture: allowed exactly when its bake fits in this machine's memory
        needs = TEXTURE_BAKE_BYTES_PER_TEXEL * 8192**2
        if needs <= machine_memory_bytes():
            load_config(None, overrides)
            return
        needle = "more than this machine"
    with pytest.raises(ConfigError, match=needle):
        load_config(None, overrides)


def test_batch_rays_against_the_pixels_of_the_photos(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _rgb(photos / f"p{i}.png", seed=i)
    code, out = recon("run", str(photos), "--out", str(tmp_path / "scene"), "--set", "train.max_side=32",
                      "--set", "train.batch_rays=4000")
    assert_clean_error(code, out, "train.batch_rays", "3 photo(s)", "3,072")
    assert not (tmp_path / "scene" / "01_poses").exists()


# ------------------------------------------------------------------------------------------------ paths


def test_unicode_and_spaces_in_paths_and_symlinked_folder(tmp_path: Path) -> None:
    """Import via a symlinked folder, with unicode and spaces in both the capture and the output path."""
    real = tmp_path / "phötos été 📷" / "cap ture"
    _capture(real)
    link = tmp_path / "lïnk to capture"
    link.symlink_to(real, target_is_directory=True)
    scene = tmp_path / "scène out" / "résultat 1"
    code, out = _run_import(link, scene)
    assert code == 0, out
    loaded = load_scene(scene / "02_scene", link)
    assert len(loaded.frames) == 4
    assert all(loaded.image_path(f).is_file() for f in loaded.frames)
    code, out = _run_import(link, scene)
    assert code == 0 and "Traceback" not in out


@pytest.mark.slow  # ~25 s of SfM on 2 cores
def test_symlinked_photo_folder_runs_structure_from_motion(tmp_path: Path) -> None:
    """Plain photos (no poses) reached through a symlink, and symlinked photos inside it: SfM registers them."""
    real = tmp_path / "real photos"
    real.mkdir()
    for i, src in enumerate(sorted((SAMPLE / "images").glob("*.jpg"))):
        if i % 2:
            (real / src.name).symlink_to(src)
        else:
            shutil.copy(src, real / src.name)
    link = tmp_path / "photos link"
    link.symlink_to(real, target_is_directory=True)
    code, out = recon("run", str(link), "--out", str(tmp_path / "scene"), "--until", "poses", "-q")
    assert code == 0, out
    summary = json.loads((tmp_path / "scene" / "manifest.json").read_text())["stages"]["poses"]["summary"]
    assert summary["registered"] == 40, summary


# ------------------------------------------------------------------------------------------------ fuzz


def assert_valid_scene(scene: Scene) -> None:
    """What every importer promises downstream: cameras with finite rigid poses and positive intrinsics."""
    assert scene.frames
    for f in scene.frames:
        c2w = np.asarray(f.c2w)
        assert c2w.shape == (4, 4) and np.all(np.isfinite(c2w))
        assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-6)
        assert np.linalg.det(c2w[:3, :3]) > 0
        assert f.w >= 1 and f.h >= 1
        assert all(math.isfinite(v) for v in (f.fl_x, f.fl_y, f.cx, f.cy, f.k1, f.k2, f.p1, f.p2))
        assert f.fl_x > 0 and f.fl_y > 0
        assert f.split in (None, "train", "val", "test")


_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12), st.just("images/v0.png"), st.just("../x.png"), st.just("a\x00b"), st.just("x" * 300),
)
_json = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=20)
_matrix = st.one_of(
    _json,
    st.lists(st.lists(st.floats(-3, 3), min_size=4, max_size=4), min_size=3, max_size=5),
    st.sampled_from([_pose(0.3), np.eye(4).tolist(), (2 * np.eye(4)).tolist()]),
)
_keys = ["file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "camera_angle_x", "split", "near", "far"]
_frame = st.fixed_dictionaries(
    {"transform_matrix": _matrix, "file_path": st.sampled_from(["images/v0.png", "images/v1", "images/", "../v0.png", "/etc/hostname", "\x00", 7])},
    optional={k: _json for k in _keys if k not in ("file_path", "transform_matrix")},
)
_doc = st.one_of(
    _json,
    st.fixed_dictionaries({"frames": st.lists(_frame, max_size=3)}, optional={k: _json for k in _keys[2:]}),
    st.fixed_dictionaries(
        {"frames": st.lists(_frame, min_size=1, max_size=3), "fl_x": st.floats(-10, 100), "w": st.integers(-2, 64), "h": st.integers(-2, 64)}
    ),
)


@pytest.fixture(scope="module")
def fuzz_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz") / "cap"
    _capture(folder, n=2)
    (folder / "images" / "notes.png").write_text("text, not an image")
    return folder


FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@FUZZ
@given(doc=_doc)
def test_fuzz_import_transforms(fuzz_capture: Path, doc: object) -> None:
    path = fuzz_capture / "transforms.json"
    path.write_text(json.dumps(doc))
    try:
        scene = import_transforms(path)
    except InputError:
        return
    assert_valid_scene(scene)


@FUZZ
@given(doc=_doc, fmt=st.sampled_from(["recon-scene", None]))
def test_fuzz_load_scene(fuzz_capture: Path, doc: object, fmt: str | None) -> None:
    folder = fuzz_capture / "02_scene"
    folder.mkdir(exist_ok=True)
    if isinstance(doc, dict) and fmt:
        doc = {**doc, "format": fmt}
    (folder / "scene.json").write_text(json.dumps(doc))
    try:
        scene = load_scene(folder)
    except InputError:
        return
    assert_valid_scene(scene)


_arrays = st.one_of(
    st.builds(lambda s, v: np.full(s, v), st.lists(st.integers(0, 4), max_size=5).map(tuple), st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(lambda s: np.zeros(s, dtype=np.uint8), st.lists(st.integers(0, 9), max_size=4).map(tuple)),
    st.sampled_from([np.array("text"), np.array([1, 2, 3]), np.eye(4)[None], np.array(10.0), np.array(True)]),
)


@FUZZ
@given(
    images=_arrays | st.just(np.random.default_rng(0).random((2, 8, 8, 3))),
    poses=_arrays | st.just(np.stack([np.eye(4), np.asarray(_pose(1.0))])),
    focal=_arrays,
    drop=st.sampled_from([None, "images", "poses", "focal"]),
)
def test_fuzz_import_npz(tmp_path_factory: pytest.TempPathFactory, images: np.ndarray, poses: np.ndarray, focal: np.ndarray, drop: str | None) -> None:
    folder = tmp_path_factory.mktemp("npz")
    arrays = {"images": images, "poses": poses, "focal": focal}
    if drop:
        arrays.pop(drop)
    path = _npz(folder / "data.npz", **arrays)
    try:
        scene = import_npz(path, folder / "images")
    except InputError:
        return
    assert_valid_scene(scene)


# ------------------------------------------------------------------------------------------------ sizes, links, manifest


def _png_header(path: Path, width: int, height: int) -> None:
    """A PNG that is only a header (IHDR claiming width × height, RGB 8-bit) and an end: 57 bytes, no pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))


@pytest.mark.parametrize("side", [30000, 21000], ids=["over-twice-the-limit", "over-the-limit"])
def test_huge_png_header_is_refused_before_decoding(tmp_path: Path, side: int) -> None:
    """PIL refuses 30000² itself (over twice the limit); 21000² only warns, and recon refuses it from the header."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        _rgb(photos / f"p{i}.png", size=64, seed=i)
    _png_header(photos / "huge.png", side, side)
    assert (photos / "huge.png").stat().st_size < 100
    with pytest.raises(InputError, match="huge.png.*too large|huge.png.*Mpx"):
        read_image(photos / "huge.png", max_side=400)
    code, out = recon("run", str(photos), "--out", str(tmp_path / "scene"), "--until", "poses", "-q")
    assert_clean_error(code, out, "huge.png", "Downscale it")


def test_video_frames_over_the_pixel_limit_are_refused_from_the_header(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A tiny clip against a limit lowered below its frames: refused with the header's size, as 16000² would be."""
    import cv2

    import recon.capture.video

    clip = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 10, (96, 64))
    for i in range(3):
        writer.write(np.full((64, 96, 3), 40 * i, np.uint8))
    writer.release()
    assert recon.capture.video.probe(clip).width == 96
    monkeypatch.setattr(recon.capture.video, "MAX_PIXELS", 96 * 64 - 1)
    with pytest.raises(InputError, match=r"clip.mp4 is 96×64 px"):
        recon.capture.video.probe(clip)


def test_symlink_loop_as_the_photos_folder(tmp_path: Path) -> None:
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    (tmp_path / "self").symlink_to(tmp_path / "self")
    for name in ("a", "self"):
        code, out = recon("run", str(tmp_path / name), "--out", str(tmp_path / f"scene-{name}"))
        assert_clean_error(code, out, str(tmp_path / name), "loops or points to nothing")


@pytest.mark.parametrize("version", [0, -1, MANIFEST_VERSION + 1], ids=["zero", "negative", "future"])
def test_manifest_of_an_unknown_version_is_refused(tmp_path: Path, version: int) -> None:
    cap = tmp_path / "cap"
    _capture(cap)
    scene = tmp_path / "scene"
    assert _run_import(cap, scene)[0] == 0
    manifest = scene / "manifest.json"
    data = json.loads(manifest.read_text())
    data["version"] = version
    manifest.write_text(json.dumps(data))
    code, out = _run_import(cap, scene)
    assert_clean_error(code, out, "manifest.json", f"manifest version {version}", "give --out a new folder")
    assert ("upgrade recon" in out) == (version > MANIFEST_VERSION)
    assert_clean_error(*recon("status", str(scene)), f"manifest version {version}")
    assert json.loads(manifest.read_text())["version"] == version  # refused, not rewritten


def test_a_folder_of_raw_files_or_of_subfolders_says_what_to_do(tmp_path: Path) -> None:
    raw = tmp_path / "raw"
    raw.mkdir()
    for i in range(3):
        (raw / f"IMG_{i}.CR2").write_bytes(b"II*\x00raw")
    code, out = recon("run", str(raw), "--out", str(tmp_path / "s1"))
    assert_clean_error(code, out, "No photos found", "camera RAW files (.CR2)", "export them as JPEG")
    nested = tmp_path / "nested"
    for i, sub in enumerate(["day1", "day2", "DCIM/100APPLE"]):
        (nested / sub).mkdir(parents=True)
        for k in range(i + 1):
            _rgb(nested / sub / f"{k}.png", seed=i)
    code, out = recon("run", str(nested), "--out", str(tmp_path / "s2"))
    # a phone's folders are two down; the one with the most photos is the example
    assert_clean_error(code, out, "No photos found", "DCIM/100APPLE/ (3), day2/ (2), day1/ (1)",
                       str(nested / "DCIM" / "100APPLE"))
    assert not (tmp_path / "s1").exists() and not (tmp_path / "s2").exists()  # said before the scene folder is made


def test_byte_identical_copies_of_a_photo_are_left_out_and_named(tmp_path: Path) -> None:
    from recon.stages.poses import drop_copies

    for i in range(3):
        _rgb(tmp_path / f"IMG_{i}.png", seed=i)
    (tmp_path / "IMG_1 (1).png").write_bytes((tmp_path / "IMG_1.png").read_bytes())
    (tmp_path / "IMG_0 copy.png").write_bytes((tmp_path / "IMG_0.png").read_bytes())
    photos = sorted(tmp_path.glob("*.png"))
    kept, copies = drop_copies(photos)
    assert [p.name for p in kept] == ["IMG_0.png", "IMG_1.png", "IMG_2.png"]
    assert {c.name: o.name for c, o in copies.items()} == {"IMG_0 copy.png": "IMG_0.png", "IMG_1 (1).png": "IMG_1.png"}


def test_the_look_for_photos_below_a_folder_is_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Given a home folder, the no-photos error must not walk the disk: so deep, so many folders, no links."""
    from recon.capture import images

    for name in ("a", "b", "c/d", "e/f/g/h"):
        (tmp_path / name).mkdir(parents=True)
        _rgb(tmp_path / name / "p.png", seed=0)
    (tmp_path / "link").symlink_to(tmp_path / "a", target_is_directory=True)
    assert [d.relative_to(tmp_path).as_posix() for d, _ in images.photo_folders_below(tmp_path)] == ["a", "b", "c/d"]
    monkeypatch.setattr(images, "NESTED_MAX_FOLDERS", 3)  # the folder itself, a, b
    assert [d.name for d, _ in images.photo_folders_below(tmp_path)] == ["a", "b"]


def test_unusable_photos_are_all_named_before_the_scene_folder_is_made(tmp_path: Path) -> None:
    """An empty file, text named like a photo and a thumbnail: one message names the three with what each is, exit
    2, and no scene folder is made (the headers are read before it)."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(4):
        _rgb(photos / f"p{i}.png", size=64, seed=i)
    (photos / "empty.jpg").write_bytes(b"")
    (photos / "notes.png").write_text("not a picture")
    _rgb(photos / "thumb.png", size=20)
    code, out = recon("run", str(photos), "--out", str(tmp_path / "scene"), "--until", "poses", "-q")
    assert_clean_error(code, out, "3 of the 7 photos", "empty.jpg (an empty file)", "notes.png (not an image",
                       "thumb.png (20×20 px", "Remove them from the folder")
    assert not (tmp_path / "scene").exists()
