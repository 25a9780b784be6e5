"""Normalization at the extremes: invariance to any similarity of the source world, exact round trips back to
the source frame (scene and exported mesh), and degenerate captures (a correct result or a clear InputError,
never NaN in scene.json)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from recon.camera import look_at
from recon.capture.normalization import normalize, similarity, transform_c2w
from recon.capture.scene import Frame, Scene, load_scene
from recon.config import NormalizeConfig
from recon.errors import InputError
from recon.geometry.export import export_transform


def frame(i: int, c2w: np.ndarray) -> Frame:
    return Frame(f"/p/{i:03d}.jpg", c2w, 400.0, 400.0, 200.0, 150.0, 400, 300)


def ring(n: int = 16, radius: float = 4.0, n_points: int = 800, seed: int = 0) -> Scene:
    """Cameras on a wavy ring around a blob of points at the origin (+Z up)."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = np.radians(20 + 15 * np.sin(3 * az))
        eye = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        frames.append(frame(i, look_at(eye, np.zeros(3))))
    points = rng.normal(size=(n_points, 3)) * 0.3
    return Scene(frames=frames, points=points, point_colors=np.zeros((n_points, 3), np.uint8))


def moved(scene: Scene, T: np.ndarray) -> Scene:
    """The same capture seen in a world moved by the similarity T (4, 4)."""
    frames = [Frame(**{**f.__dict__, "c2w": transform_c2w(T, f.c2w)}) for f in scene.frames]
    return Scene(frames=frames, points=scene.points @ T[:3, :3].T + T[:3, 3], point_colors=scene.point_colors,
                 point_visibility=scene.point_visibility)


def quat_rotation(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def assert_scene_finite(scene: Scene) -> None:
    """Everything that goes into scene.json / points.npz is finite."""
    doc = scene.to_json()
    json.dumps(doc, allow_nan=False)  # raises ValueError on NaN/inf anywhere in the document
    assert np.all(np.isfinite(scene.points))
    for f in scene.frames:
        assert 0 < f.near < f.far < math.inf


quaternions = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(lambda q: np.linalg.norm(q) > 0.1)
log_scales = st.floats(-4, 4)
offsets = st.tuples(*[st.sampled_from([0.0, 1.0, -1e3, 1e6, -1e6]) for _ in range(3)])


@given(q=quaternions, log_scale=log_scales, offset=offsets)
def test_normalize_is_invariant_to_any_similarity(q, log_scale: float, offset) -> None:
    base = ring()
    ref = normalize(base, NormalizeConfig())
    scale = 10.0**log_scale
    T = similarity(scale, quat_rotation(q), np.zeros(3))
    T[:3, 3] = offset
    src = moved(base, T)
    out = normalize(src, NormalizeConfig())
    assert out.capture == ref.capture == "object"
    # float64 carries ~16 digits: an offset of 1e6 on a 1e-4 scene leaves ~6 significant digits of the ring
    rel = 1e-6 + 1e-15 * max(np.abs(offset)) / scale
    for a, b in zip(ref.frames, out.frames, strict=True):
        np.testing.assert_allclose(b.c2w, a.c2w, atol=max(1e-6, 10 * rel))
        assert b.near == pytest.approx(a.near, rel=max(1e-5, 10 * rel))
        assert b.far == pytest.approx(a.far, rel=max(1e-5, 10 * rel))
    np.testing.assert_allclose(out.aabb, ref.aabb, atol=max(1e-6, 10 * rel))
    assert_scene_finite(out)
    # the stored similarity maps every camera back onto the source exactly (to float64 rounding)
    for f, s in zip(out.frames, src.frames, strict=True):
        back = transform_c2w(out.source_from_world, f.c2w)
        np.testing.assert_allclose(back[:3, 3], s.c2w[:3, 3], rtol=0, atol=1e-9 * (scale * 5 + max(np.abs(offset))))
        np.testing.assert_allclose(back[:3, :3], s.c2w[:3, :3], atol=1e-9)


@given(q=quaternions, log_scale=log_scales, offset=offsets, real_size=st.sampled_from([0.0, 0.25, 30.0]))
def test_mesh_exported_in_source_frame_lands_on_the_source_points(q, log_scale: float, offset, real_size: float) -> None:
    base = ring()
    scale = 10.0**log_scale
    T = similarity(scale, quat_rotation(q), np.zeros(3))
    T[:3, 3] = offset
    src = moved(base, T)
    scene = normalize(src, NormalizeConfig())
    # a "mesh" whose vertices are the normalized sparse points: frame="source" must return the source points
    verts = scene.points.astype(np.float64)
    transform, why = export_transform(verts, "source", scene.source_from_world, real_size)
    assert "source frame" in why
    mapped = verts @ transform[:3, :3].T + transform[:3, 3]
    if real_size == 0:
        np.testing.assert_allclose(mapped, src.points, rtol=0, atol=1e-9 * (scale + max(np.abs(offset))))
    else:  # only a uniform scale about the source origin on top: the shape and the requested size are kept
        side = np.ptp(mapped, axis=0).max()
        assert side == pytest.approx(real_size, rel=1e-9)
        np.testing.assert_allclose(mapped * (np.ptp(src.points, axis=0).max() / side), src.points,
                                   rtol=0, atol=1e-7 * (scale + max(np.abs(offset))))


def test_scene_json_round_trip_keeps_the_similarity_exact(tmp_path: Path) -> None:
    T = similarity(3e-4, quat_rotation((0.3, -0.2, 0.9, 0.1)), np.zeros(3))
    T[:3, 3] = (1e6, -2e5, 7.0)
    src = moved(ring(), T)
    scene = normalize(src, NormalizeConfig())
    scene.save(tmp_path)
    loaded = load_scene(tmp_path)
    back = transform_c2w(loaded.source_from_world, loaded.frames[3].c2w)
    np.testing.assert_allclose(back[:3, 3], src.frames[3].c2w[:3, 3], rtol=0, atol=1e-9)
    json.loads((tmp_path / "scene.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in scene.json"))


# ----------------------------------------------------------------------------------------- degenerate captures
BLOB = np.random.default_rng(1).normal(size=(400, 3)) * 0.3


@pytest.mark.parametrize("with_points", [True, False])
def test_rotation_only_capture_is_rejected_by_name(with_points: bool) -> None:
    # every camera at one point, turning around: no parallax, no depth
    frames = [frame(i, look_at(np.array([1e6, 0, 0]), np.array([1e6 + np.cos(a), np.sin(a), 0.1])))
              for i, a in enumerate(np.linspace(0, 6, 12))]
    pts = BLOB * 10 + [1e6, 0, 0] if with_points else np.zeros((0, 3))
    with pytest.raises(InputError, match="same point.*rotation-only"):
        normalize(Scene(frames=frames, points=pts), NormalizeConfig())


@pytest.mark.parametrize("n", [1, 3])
def test_a_single_viewpoint_is_rejected(n: int) -> None:
    frames = [frame(i, look_at(np.array([4.0, 0, 1]), np.zeros(3))) for i in range(n)]
    with pytest.raises(InputError, match="same point"):
        normalize(Scene(frames=frames, points=BLOB), NormalizeConfig())


@pytest.mark.parametrize("with_points", [True, False])
def test_cameras_on_a_line_give_a_finite_scene(with_points: bool) -> None:
    # a sideways sweep looking at the object, and a forward-facing dolly: both valid captures
    sweep = [frame(i, look_at(np.array([4.0, i - 5.0, 0.5]), np.zeros(3))) for i in range(10)]
    dolly = [frame(i, look_at(np.array([0.1 * i, 0, 0]), np.array([0.1 * i, 10.0, 0]))) for i in range(10)]
    for frames in (sweep, dolly):
        scene = normalize(Scene(frames=frames, points=BLOB if with_points else np.zeros((0, 3))), NormalizeConfig())
        assert_scene_finite(scene)
        assert np.abs(scene.aabb).max() == pytest.approx(1.0)
        ups = np.stack([f.c2w[:3, 1] for f in scene.frames])
        assert ups.mean(0)[2] > 0.9  # still upright


def test_two_cameras_give_a_finite_scene() -> None:
    frames = [frame(i, look_at(4 * np.array([np.cos(a), np.sin(a), 0.25]), np.zeros(3))) for i, a in enumerate([0, 0.5])]
    for pts in (BLOB, np.zeros((0, 3))):
        assert_scene_finite(normalize(Scene(frames=frames, points=pts), NormalizeConfig()))


def test_points_at_infinity_are_dropped_and_visibility_renumbered() -> None:
    base = ring()
    pts = base.points.copy()
    pts[[0, 5]] = np.inf
    pts[7] = [np.nan, 1, 1]
    pts[9] = [-np.inf, np.inf, 0]
    vis = {base.frames[0].name: np.array([1, 5, 6, 8, 10])}
    scene = normalize(Scene(frames=base.frames, points=pts, point_colors=np.arange(len(pts) * 3).reshape(-1, 3) % 255,
                            point_visibility=vis), NormalizeConfig())
    assert_scene_finite(scene)
    assert len(scene.points) == len(pts) - 4
    keep = np.all(np.isfinite(pts), axis=1)
    # frame 0 still sees the same points after renumbering (5 is gone; 1, 6, 8, 10 remain)
    seen = scene.points[scene.point_visibility[base.frames[0].name]]
    T = scene.world_from_source
    np.testing.assert_allclose(seen, pts[[1, 6, 8, 10]] @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    np.testing.assert_array_equal(scene.point_colors, (np.arange(len(pts) * 3).reshape(-1, 3) % 255)[keep])


def test_one_far_outlier_point_does_not_change_the_box() -> None:
    base = ring()
    ref = normalize(base, NormalizeConfig())
    pts = base.points.copy()
    pts[3] = [1e12, -1e12, 1e12]
    out = normalize(Scene(frames=base.frames, points=pts), NormalizeConfig())
    np.testing.assert_allclose(out.aabb, ref.aabb, atol=0.02)
    assert_scene_finite(out)
    # forward-facing: the outlier is far beyond the scene; the percentile box ignores it
    dolly = [frame(i, look_at(np.array([0.1 * i, 0, 0]), np.array([0.1 * i, 10.0, 0]))) for i in range(12)]
    rng = np.random.default_rng(0)
    fw = np.c_[rng.uniform(-3, 3, 500), rng.uniform(5, 30, 500), rng.uniform(-2, 2, 500)]
    a = normalize(Scene(frames=dolly, points=fw), NormalizeConfig())
    fw[0] = [0, 1e9, 0]
    b = normalize(Scene(frames=dolly, points=fw), NormalizeConfig())
    np.testing.assert_allclose(b.aabb, a.aabb, atol=0.02)
    assert_scene_finite(b)


def test_a_thin_part_stays_in_the_box_and_stray_points_do_not() -> None:
    # the generator's thin scene: a rod of few points stands out of the object (under 2 % of the points, so a
    # 2 %/98 % percentile box cut it), while stray triangulations float alone further out
    base = ring()
    blob = base.points
    spacing = float(np.median(np.linalg.norm(blob[:, None] - blob[None], axis=-1)[~np.eye(len(blob), dtype=bool)]
                              .reshape(len(blob), -1).min(axis=1)))
    top = 0.5 + 2 * spacing * np.arange(6)  # a chain 2 spacings apart, up to well above the blob
    rod = np.c_[np.full(6, 0.1), np.zeros(6), top]
    strays = np.array([[1.6, 0.0, 0.0], [0.0, -1.6, 0.3], [-1.2, 1.2, -0.6]])
    pts = np.concatenate([blob, rod, strays])
    assert len(rod) / len(pts) < 0.02 and top[-1] > np.percentile(pts[:, 2], 98) + 0.5
    scene = normalize(Scene(frames=base.frames, points=pts), NormalizeConfig(box_margin=0.0))
    to_world = np.linalg.inv(scene.source_from_world)
    inside = lambda p: np.all((p @ to_world[:3, :3].T + to_world[:3, 3] >= scene.aabb[0] - 1e-9)
                              & (p @ to_world[:3, :3].T + to_world[:3, 3] <= scene.aabb[1] + 1e-9), axis=1)
    assert inside(rod).all()  # the rod's tip is in the box
    assert not inside(strays).any()  # no stray point is


@pytest.mark.parametrize("arc_deg", [40.0, 60.0, 90.0])
def test_level_photos_from_a_narrow_arc_looking_down_come_out_upright(arc_deg: float) -> None:
    """Hand-held photos of an object's front only, looking down 15-50° with a little roll: their right vectors are
    level and span the level plane even over a 40° arc, so up is orthogonal to them, not their mean up vector (which
    leans back by their mean downward look)."""
    rng = np.random.default_rng(int(arc_deg))
    frames = []
    for i in range(24):
        az, el = np.radians(arc_deg * (((0.5 + 0.618034 * i) % 1) - 0.5)), np.radians(rng.uniform(15, 50))
        c2w = look_at(4.0 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)]), np.zeros(3))
        roll = np.radians(rng.uniform(-2, 2))
        c2w[:3, :3] = c2w[:3, :3] @ np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0],
                                               [0, 0, 1]])
        frames.append(frame(i, c2w))
    from recon.capture.normalization import estimate_up

    up, why = estimate_up(np.stack([f.c2w for f in frames]), "auto")
    assert np.degrees(np.arccos(up @ [0, 0, 1])) < 2.0, why


@pytest.mark.parametrize("seed", range(4))
def test_top_down_cameras_with_random_roll_come_out_upright(seed: int) -> None:
    # up vectors all horizontal in random directions (their mean can still be long): up is the normal of the
    # plane of the camera centres, on the side the cameras look down from
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(12):
        a = rng.uniform(0, 2 * np.pi)
        eye = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 5.0])
        frames.append(frame(i, look_at(eye, np.array([0.0, 0, 0]), up=(np.cos(a), np.sin(a), 0))))
    scene = normalize(Scene(frames=frames, points=BLOB), NormalizeConfig())
    views = np.stack([-f.c2w[:3, 2] for f in scene.frames])
    assert views.mean(0)[2] < -0.9, scene.notes["up"]  # cameras look down the new -Z


def test_up_cannot_be_told_gives_a_clear_error_and_the_override_works() -> None:
    # up vectors that cancel (±X, ±Y, ±Z, ±diagonal), centres on the corners of a cube (isotropic: no plane)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    ups = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1], [-1, -1, -1]], float)
    frames = []
    for i, (centre, up) in enumerate(zip(corners, ups, strict=True)):
        up /= np.linalg.norm(up)
        right = np.cross(up, [0.3, 0.5, 0.8])
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, np.cross(right, up), centre
        frames.append(frame(i, c2w))
    with pytest.raises(InputError, match="which way is up.*normalize.up"):
        normalize(Scene(frames=frames, points=BLOB), NormalizeConfig())
    assert_scene_finite(normalize(Scene(frames=frames, points=BLOB), NormalizeConfig(up="z")))


@pytest.mark.parametrize("tilt", [0.0, 1e-12, 4e-6, 3e-5])
def test_rotation_between_nearly_opposite_vectors_is_exact(tilt: float) -> None:
    # regression: within ~4.5e-5 rad of opposite, the small tilt was dropped (180° flip only), which tilted the
    # normalized scene of a world rotated by ~180° about a horizontal axis
    from recon.capture.normalization import rotation_between

    a = np.array([0.0, np.sin(tilt), -np.cos(tilt)])
    b = np.array([0.0, 0.0, 1.0])
    R = rotation_between(a, b)
    np.testing.assert_allclose(R @ a, b, rtol=0, atol=1e-15)
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-15)


def test_an_object_box_grows_to_hold_what_the_masks_show_and_no_further() -> None:
    # the masks' visual hull (`recon.stages.normalize`) reaches past the sparse points: a plain part has no points
    base = ring()
    ref = normalize(base, NormalizeConfig())
    assert ref.capture == "object"
    beyond = np.array([[0.0, 0.0, 1.4], [0.2, -0.1, 0.0]])  # above the blob (points reach ~1), and inside it
    grown = normalize(base, NormalizeConfig(), holds=beyond)
    inside = lambda s, p: np.all((p @ np.linalg.inv(s.source_from_world)[:3, :3].T
                                  + np.linalg.inv(s.source_from_world)[:3, 3] >= s.aabb[0] - 1e-9)
                                 & (p @ np.linalg.inv(s.source_from_world)[:3, :3].T
                                    + np.linalg.inv(s.source_from_world)[:3, 3] <= s.aabb[1] + 1e-9), axis=1)
    assert not inside(ref, beyond[:1]).all() and inside(grown, beyond).all()
    assert "visual hull" in grown.notes["box"] and "visual hull" not in ref.notes["box"]
    assert not inside(grown, beyond[:1] + [0.0, 0.0, 0.3]).all()  # to what the hull holds, and its margin
    world = (beyond[:1] - 0.0) @ np.linalg.inv(grown.source_from_world)[:3, :3].T + np.linalg.inv(grown.source_from_world)[:3, 3]
    assert (world <= grown.region[1] + 1e-9).all() and (world >= grown.region[0] - 1e-9).all()  # the mesh's too
    same = normalize(base, NormalizeConfig(), holds=beyond[1:])  # what the box holds already changes nothing
    np.testing.assert_allclose(same.aabb, ref.aabb)
    assert "visual hull" not in same.notes["box"]


def test_the_masks_hull_is_the_training_photos_alone(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    # held-out photos score the result; their masks must not shape the box (a test set's silhouettes would)
    from dataclasses import replace
    from types import SimpleNamespace

    import recon.stages.normalize as stage
    from recon.app.progress import Reporter
    from recon.evaluation.views import View

    frames = []
    for i in range(12):
        az = 2 * math.pi * i / 12
        eye = 3.0 * np.array([math.cos(az), math.sin(az), 0.4])
        frames.append(Frame(f"p{i:02d}.png", look_at(eye, np.zeros(3)), 60.0, 60.0, 32.0, 32.0, 64, 64,
                            split="test" if i % 4 == 0 else "train"))
    scene = Scene(frames=frames, aabb=np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), capture="object", has_alpha=True)
    read: list[str] = []

    def silhouette(scene: Scene, frame: Frame, side: int, keep_alpha: bool) -> View:
        read.append(frame.split or "")
        image = np.zeros((64, 64, 4), np.uint8)
        image[22:42, 22:42, 3] = 255  # an object at the centre, seen by every photo
        return View(frame.stem, image, frame.c2w, (60.0, 60.0, 32.0, 32.0), 0.0, 0.0)

    monkeypatch.setattr(stage, "load_view", silhouette)
    ctx = SimpleNamespace(scene_dir=tmp_path, folder="02_scene", out=tmp_path / "out", report=Reporter(quiet=True))
    assert stage._masks_hull(ctx, scene) is not None
    assert read == ["train"] * 9
    read.clear()
    unsplit = Scene(frames=[replace(f, split=None) for f in frames], aabb=scene.aabb, capture="object", has_alpha=True)
    stage._masks_hull(ctx, unsplit)  # a scene without a split: every photo is a training photo
    assert read == [""] * 12
