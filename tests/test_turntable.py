"""Turntable captures (`recon.capture.turntable`): a camera on a tripod, the object turning in front of the still room.

The generated turntable capture (fixtures/gen_tabletop.py, turntable=True) knows its object's masks and its cameras in
the object's frame; a handheld capture of the same room, the shipped sample and copies of one photo are the captures
that must not be taken for one.
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from recon.app.cli import app
from recon.capture.images import read_image
from recon.capture.scene import load_scene
from recon.capture.turntable import _log_gray, _textured, feature_mask, find_turntable, turntable_verdict

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "fixtures"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import gen_tabletop  # noqa: E402

from test_sfm import pose_errors  # noqa: E402

VIEWS = 24
ONE_THREAD = ["--set", "poses.num_threads=1"]
"""COLMAP on one thread gives the same cameras every run (on several, its threads make each run's sparse points,
and so the masks, differ)."""


@pytest.fixture(scope="module")
def turntable(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return gen_tabletop.generate(tmp_path_factory.mktemp("turntable"), views=VIEWS, size="480x360", realistic=True,
                                 turntable=True, mesh_res=64)


@pytest.fixture(scope="module")
def posed(turntable: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """`recon run --until poses` on the turntable's photos alone, once for the module: (photos, scene, output).
    A test that goes on from it works on a copy (`scene_copy`)."""
    folder = tmp_path_factory.mktemp("turntable_posed")
    alone = photos_alone(turntable, folder / "photos")
    result = CliRunner().invoke(app, ["run", str(alone), "--out", str(folder / "scene"), "--until", "poses",
                                      *ONE_THREAD])
    assert result.exit_code == 0, result.output
    return alone, folder / "scene", result.output


def scene_copy(posed: tuple[Path, Path, str], into: Path) -> Path:
    """A copy of the posed scene the same command resumes (its poses stage up to date)."""
    return Path(shutil.copytree(posed[1], into, ignore=shutil.ignore_patterns(".lock", ".work")))


def photos(capture: Path) -> list[np.ndarray]:
    return [read_image(p) for p in sorted((capture / "images").glob("*.jpg"))]


def photos_alone(capture: Path, folder: Path, every: int = 1) -> Path:
    """The capture's photos (every ``every``-th) linked into ``folder``, without its masks/ beside them, as a user's
    photos come."""
    folder.mkdir()
    for photo in sorted((capture / "images").glob("*.jpg"))[::every]:
        (folder / photo.name).symlink_to(photo)
    return folder


def turning_pixels(capture: Path) -> list[np.ndarray]:
    """Per photo, (h, w) bool: what turns with the object (the object and its platter), traced as the generator
    rendered it in the object's frame."""
    doc = json.loads((capture / "transforms.json").read_text())
    room = gen_tabletop.Room(turntable=True)
    k = gen_tabletop.g.default_intrinsics(doc["w"], doc["h"], fov_x_deg=50.0)
    lens = gen_tabletop.Lens(doc["k1"], doc["k2"])
    jj, ii = np.mgrid[0:doc["h"], 0:doc["w"]]
    turning = []
    for frame in doc["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        rays = gen_tabletop.pixel_rays(c2w, k, lens, ii.ravel() + 0.5, jj.ravel() + 0.5)
        labels = gen_tabletop.trace(room, c2w[:3, 3], rays, list(range(len(room.props))), 0.0)[1]
        turning.append(np.isin(labels, room.turning).reshape(ii.shape))
    return turning


def test_a_turntable_capture_is_found_with_its_camera_positions_and_the_object(turntable: Path) -> None:
    """The object and its platter fill half of each photo; the room around them still tells the camera stood
    still."""
    images = photos(turntable)
    found = find_turntable(images)
    assert found is not None
    info = json.loads((turntable / "scene_info.json").read_text())
    rings = np.asarray(info["turntable"]["ring"])
    positions = [np.flatnonzero(rings == r).tolist() for r in range(rings.max() + 1)]
    assert sorted(sorted(g) for g in found.groups) == positions
    shares = []
    for i, (mask_path, turns) in enumerate(zip(sorted((turntable / "masks").glob("*.png")), turning_pixels(turntable))):
        size = found.moving[i].shape[::-1]
        true = np.asarray(read_image(mask_path))[..., 0] > 0.5
        true = cv2.resize(true.astype(np.uint8), size, interpolation=cv2.INTER_AREA) > 0
        turns = cv2.resize(turns.astype(np.uint8), size, interpolation=cv2.INTER_AREA) > 0
        shares.append(turns.mean())
        moving = found.moving[i]
        assert (moving & true).sum() >= 0.97 * true.sum(), i  # the object's pixels keep their features
        assert (moving & ~turns).sum() <= 0.3 * turns.sum(), i  # and little of the still room does
        room = found.background[i]
        assert (room & turns).sum() <= 0.01 * turns.sum(), i  # what is called the still room does not turn
        textured = _textured(_log_gray(images[i]))
        assert room[~turns & textured].mean() > 0.75, i  # and most of the room's texture is known as the room
    assert np.median(shares) > 0.4, shares
    assert "turntable" in found.reason() and f"{VIEWS} of {VIEWS} photos" in found.reason()
    full = feature_mask(found, 0, (480, 360))
    assert full.shape == (360, 480) and 0.02 < full.mean() < 0.6


def test_photos_from_a_moving_camera_are_not_a_turntable(tmp_path: Path) -> None:
    handheld = gen_tabletop.generate(tmp_path / "handheld", views=8, size="480x360", realistic=True, mesh_res=64)
    assert find_turntable(photos(handheld)) is None
    found, reason = turntable_verdict(photos(REPO / "fixtures" / "sample"))
    assert found is None and reason.startswith("turntable: no (no 6 or more photos share one still camera position")
    assert "poses.turntable=off" in reason


def test_a_turntable_in_front_of_a_white_sweep_is_left_to_ordinary_sfm(tmp_path: Path) -> None:
    """A studio's plain sweep shows no texture that could pin the cameras to the tripod: nothing to recognise, and
    SfM matches the object and platter as they turn."""
    sweep = gen_tabletop.generate(tmp_path / "sweep", views=12, size="320x240", realistic=True, turntable=True,
                                  backdrop=True, mesh_res=48)
    images = photos(sweep)
    for image, mask_path in zip(images, sorted((sweep / "masks").glob("*.png"))):
        top = _textured(_log_gray(image))[:40]  # the sweep above the object and platter
        assert top.mean() < 0.01 and (np.asarray(read_image(mask_path))[..., 0] > 0.5).mean() > 0.05
    assert find_turntable(images) is None


def test_copies_of_one_still_scene_are_not_a_turntable(turntable: Path) -> None:
    """A burst from a tripod with nothing turning: the photos agree everywhere, and nothing is left to match."""
    photo = photos(turntable)[0]
    rng = np.random.default_rng(0)
    burst = [np.clip(photo * gain + rng.normal(0, 0.01, photo.shape), 0, 1).astype(np.float32)
             for gain in (1.0, 0.95, 1.05, 1.0, 0.9, 1.1)]
    found, reason = turntable_verdict(burst)
    assert found is None and "0 of 6 photos come from still camera positions" in reason
    assert "6 more show one still scene without change (copies)" in reason


def test_a_plain_part_of_the_object_that_stays_in_place_is_not_the_still_room() -> None:
    """A plain vase on a turntable looks the same in every photo: it agrees with the median like the room does, but
    nothing says it is the room (no texture), so the masks may not take it for background."""
    rng = np.random.default_rng(0)
    h, w = 240, 320
    room = np.clip(0.5 + 0.25 * cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), 1.5) * 4, 0, 1)
    yy, xx = np.mgrid[0:h, 0:w]
    vase = (xx - 160) ** 2 + (yy - 120) ** 2 < 50 ** 2
    frames = []
    for k in range(12):  # a textured handle goes round the vase
        img = np.where(vase, 0.8, room)
        a = 2 * np.pi * k / 12
        cx, cy = 160 + 70 * np.cos(a), 120 + 30 * np.sin(a)
        handle = (xx - cx) ** 2 + (yy - cy) ** 2 < 18 ** 2
        img = np.where(handle, rng.uniform(0.1, 0.9, (h, w)), img)
        frames.append(np.repeat(img[..., None], 3, axis=2).astype(np.float32))
    found = find_turntable(frames)
    assert found is not None and [len(g) for g in found.groups] == [12]
    inner = (xx - 160) ** 2 + (yy - 120) ** 2 < 45 ** 2  # the vase less its outline (an edge is texture)
    for i in range(12):
        assert not found.background[i][inner].any(), i
        assert found.background[i][~vase].mean() > 0.6, i


def test_exposure_brackets_from_a_moving_camera_are_not_a_turntable(tmp_path: Path) -> None:
    """Three shots a position, two stops apart (clipped where too bright or dark): each position's photos agree
    wherever they are not clipped, but nothing turns."""
    handheld = gen_tabletop.generate(tmp_path / "handheld", views=6, size="480x360", realistic=True, mesh_res=64)
    brackets = [np.clip(photo * gain, 0, 1).astype(np.float32) for photo in photos(handheld) for gain in (0.5, 1, 2)]
    assert find_turntable(brackets) is None


def test_structure_from_motion_places_the_cameras_around_the_turning_object(turntable: Path, tmp_path: Path,
                                                                          posed: tuple[Path, Path, str]) -> None:
    """Features from the whole photo pin every camera to the tripod; from where the photos change, SfM recovers
    the cameras in the object's frame."""
    truth = json.loads((turntable / "transforms.json").read_text())
    ref = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in truth["frames"]}
    alone, auto_scene, auto_output = posed
    half = photos_alone(turntable, tmp_path / "every_other_photo", every=2)  # the still room wins on 12 as on 24
    off = CliRunner().invoke(app, ["run", str(half), "--out", str(tmp_path / "off"), "--until", "poses",
                                   "--set", "poses.turntable=off", *ONE_THREAD])
    # without the masks the still room wins: the cameras land far from the truth, or, with every camera pinned to
    # the tripod, too few register for SfM to go on (its usual clear error)
    unposed = off.exit_code == 2 and "Structure from motion registered only" in " ".join(off.output.split())
    assert off.exit_code == 0 or unposed, off.output
    errors = {}
    for mode, out, output in (("auto", auto_scene, auto_output), ("off", tmp_path / "off", off.output)):
        assert ("turntable:" in " ".join(output.split())) == (mode == "auto")
        if mode == "off" and unposed:
            continue
        scene = load_scene(out / "01_poses")
        est = {Path(f.file_path).stem: np.asarray(f.c2w) for f in scene.frames}
        errors[mode] = pose_errors(est, ref)
    centre, rotation, compared = errors["auto"]
    assert compared == VIEWS and centre < 0.02 and rotation < 1.0, errors
    assert unposed or errors["off"][0] > 10 * centre, errors


def test_a_turntable_capture_gets_object_masks_without_a_table_in_its_sparse_points(
        turntable: Path, tmp_path: Path, posed: tuple[Path, Path, str]) -> None:
    """The still room is in every photo but in no sparse point; in the object's frame it turns with the cameras, so
    normalize cuts the object out of the photos as it does for a capture that shows its table and room, the still
    room (the poses stage's) seeding the background where no table point can."""
    scene = scene_copy(posed, tmp_path / "scene")
    result = CliRunner().invoke(app, ["run", str(posed[0]), "--out", str(scene), "--until", "normalize",
                                      *ONE_THREAD])
    assert result.exit_code == 0, result.output
    assert "poses: up to date" in " ".join(result.output.split()), result.output  # went on from the copy
    masks = sorted((tmp_path / "scene" / "02_scene" / "masks").glob("*.png"))
    assert len(masks) == VIEWS, result.output
    ious = []
    for mask in masks:
        cut = np.asarray(read_image(mask))[..., 0] >= 0.5
        true = np.asarray(read_image(turntable / "masks" / mask.name))[..., 0] >= 0.5
        ious.append((cut & true).sum() / (cut | true).sum())
    assert np.median(ious) > 0.93 and min(ious) > 0.8, ious


def test_unsure_masks_of_a_turntable_are_used_with_a_warning(tmp_path: Path, posed: tuple[Path, Path, str],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Unmasked, a turntable's room would train as fog around the object (it turns with the cameras), so masks the
    checks call unsure are used all the same, and the user is told where to look."""
    import dataclasses

    import recon.stages.normalize as normalize_stage

    segment = normalize_stage.segment_object
    monkeypatch.setattr(normalize_stage, "segment_object",
                        lambda *a, **k: dataclasses.replace(segment(*a, **k), confident=False))
    scene = scene_copy(posed, tmp_path / "scene")
    result = CliRunner().invoke(app, ["run", str(posed[0]), "--out", str(scene), "--until", "normalize",
                                      *ONE_THREAD])
    assert result.exit_code == 0, result.output
    flat = " ".join(result.output.split())
    assert "used all the same" in flat and "masks.png" in flat, result.output
    assert len(list((tmp_path / "scene" / "02_scene" / "masks").glob("*.png"))) == VIEWS
