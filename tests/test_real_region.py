"""The object of interest: what every camera keeps in frame, above the ground plane found by RANSAC
(issue 11, "the object of interest"), and the mesh stage's region / ground cut and their overrides."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon.camera import look_at
from recon.capture.normalization import normalize
from recon.capture.region import fit_ground_plane, object_region
from recon.capture.scene import Frame, Scene
from recon.config import MeshConfig, NormalizeConfig, parse_region
from recon.errors import ConfigError
from recon.geometry.clean import clean_mesh, cut_below_plane
from recon.plans.mesh import mesh_region

W, H, FL = 320, 240, 300.0
TABLE_Z = -0.3


def cameras(n: int = 16, radius: float = 2.5) -> list[Frame]:
    frames = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = np.radians(25 + 10 * np.sin(2 * az))
        eye = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), FL, FL, W / 2, H / 2, W, H))
    return frames


def tabletop_points(rng: np.random.Generator, table: bool = True, room: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Object (a ball standing on the table), table top (z = TABLE_Z, ±3 units), room (sphere of radius 8); labels."""
    d = rng.normal(size=(600, 3))
    obj = 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)
    obj = obj[obj[:, 2] > TABLE_Z]  # the part above the table top
    parts, labels = [obj], [np.zeros(len(obj), int)]
    if table:
        t = np.column_stack([rng.uniform(-3, 3, (3000, 2)), np.full(3000, TABLE_Z) + rng.normal(0, 0.003, 3000)])
        t = t[np.linalg.norm(t[:, :2], axis=1) > 0.3]  # the ball hides the table under it
        parts.append(t)
        labels.append(np.ones(len(t), int))
    if room:
        r = rng.normal(size=(1500, 3))
        r = 8 * r / np.linalg.norm(r, axis=1, keepdims=True)
        r = r[r[:, 2] > TABLE_Z]
        parts.append(r)
        labels.append(np.full(len(r), 2))
    return np.concatenate(parts), np.concatenate(labels)


def region_of(points: np.ndarray, frames: list[Frame]):
    c2ws = np.stack([f.c2w for f in frames])
    return object_region(points, c2ws, np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in frames]),
                         np.array([[f.w, f.h] for f in frames]), np.zeros(3), np.array([0.0, 0.0, 1.0]))


def test_object_on_a_table_in_a_room_is_told_from_table_and_room() -> None:
    points, labels = tabletop_points(np.random.default_rng(0))
    region = region_of(points, cameras())
    assert region is not None and region.ground is not None
    np.testing.assert_allclose(region.ground.normal, [0, 0, 1], atol=0.01)
    assert abs(region.ground.offset - TABLE_Z) < 0.01
    kept = labels[region.points]
    assert (kept == 0).mean() > 0.97  # the region is the object...
    assert region.points[labels == 0].mean() > 0.8  # ...and most of it (its bottom rim is cut with the ground)
    assert region.background_fraction > 0.8
    assert "RANSAC" in region.reason and "ground" in region.reason


def test_floating_object_or_flat_faced_object_has_no_ground() -> None:
    rng = np.random.default_rng(1)
    points, _ = tabletop_points(rng, table=False, room=False)
    region = region_of(points, cameras())
    assert region is not None and region.ground is None and region.background_fraction < 0.05
    # a box-shaped object: its flat top and bottom are planes near "up", but they extend nowhere beyond it
    cube = rng.uniform(-0.3, 0.3, size=(2000, 3))
    axis = rng.integers(0, 3, 2000)
    cube[np.arange(2000), axis] = np.sign(rng.normal(size=2000)) * 0.3
    assert fit_ground_plane(cube, np.array([0, 0, 1.0]), np.zeros(3), 0.01, background=np.zeros(2000, bool)) is None
    region = region_of(cube, cameras())
    assert region is not None and region.ground is None and region.points.mean() > 0.99


def test_from_further_back_the_table_in_nearly_every_frame_is_still_the_ground() -> None:
    """Cameras at three times the distance keep most of the table top in frame of every photo, so few of its points
    are background: the ground is still found (the plane holding most points, with background points on it too) and
    the region is the object, not the table."""
    points, labels = tabletop_points(np.random.default_rng(3))
    frames = cameras(radius=7.5)
    c2ws = np.stack([f.c2w for f in frames])
    seen = region_of(points, frames)
    assert seen is not None and seen.ground is not None
    table = labels == 1
    background_on_table = table & ~in_frame_of_most(points, c2ws, frames)
    assert background_on_table.sum() < 0.1 * len(points)  # what the background score alone took: under its 10%
    np.testing.assert_allclose(seen.ground.normal, [0, 0, 1], atol=0.01)
    assert abs(seen.ground.offset - TABLE_Z) < 0.01
    assert (labels[seen.points] == 0).mean() > 0.97


def sphere_points(rng: np.random.Generator, center: tuple[float, float, float], radius: float,
                  n: int = 300) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_from_further_back_a_thing_beside_the_object_is_left_out_and_two_objects_side_by_side_are_kept() -> None:
    """From further back a cup beside the object stands in frame of nearly every photo too, but off to the side of
    each: it is left out. Two objects the photos frame together both sit near the photos' centres: both are kept."""
    rng = np.random.default_rng(4)
    points, labels = tabletop_points(rng, room=False)
    cup = sphere_points(rng, (2.8, 1.0, TABLE_Z + 0.15), 0.15)
    frames = cameras(radius=7.5)
    c2ws = np.stack([f.c2w for f in frames])
    everything = np.concatenate([points, cup])
    assert in_frame_of_most(cup, c2ws, frames).mean() > 0.9  # in frame of most photos, as the object is
    region = region_of(everything, frames)
    assert region is not None and region.ground is not None
    assert not region.points[len(points):].any()
    assert region.aside[len(points):].mean() > 0.3 and not (region.aside & region.points).any()  # its framed part
    alone = region_of(points, frames)  # without the cup: the same object
    assert alone is not None and (region.points[:len(points)] != alone.points).sum() <= 0.01 * alone.points.sum()
    assert (labels[alone.points] == 0).mean() > 0.97
    assert "off to the side" in region.reason and "normalize.beside=keep" in region.reason
    c2ws, intrinsics = np.stack([f.c2w for f in frames]), np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in frames])
    kept = object_region(everything, c2ws, intrinsics, np.array([[f.w, f.h] for f in frames]), np.zeros(3),
                         np.array([0.0, 0.0, 1.0]), leave_aside=False)  # normalize.beside=keep
    assert kept is not None and kept.points[len(points):].mean() > 0.4 and "off to the side" not in kept.reason
    assert not kept.aside.any()
    # two balls the photos frame together, the cameras' focus between them: neither is left out
    pair = np.concatenate([sphere_points(rng, (x, 0.0, TABLE_Z + 0.3), 0.3) for x in (-0.45, 0.45)])
    table = points[labels == 1]
    table = table[np.min([np.linalg.norm(table[:, :2] - (x, 0.0), axis=1) for x in (-0.45, 0.45)], axis=0) > 0.3]
    both = region_of(np.concatenate([pair[pair[:, 2] > TABLE_Z], table]), frames)
    assert both is not None and both.points[:len(pair[pair[:, 2] > TABLE_Z])].mean() > 0.7  # less the ground cut
    assert "off to the side" not in both.reason


def in_frame_of_most(points: np.ndarray, c2ws: np.ndarray, frames: list[Frame]) -> np.ndarray:
    from recon.capture.region import IN_VIEW_FRACTION, in_view_fraction

    return in_view_fraction(points, c2ws, np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in frames]),
                            np.array([[f.w, f.h] for f in frames])) >= IN_VIEW_FRACTION


def test_normalize_keeps_the_object_in_the_box_and_contracts_the_rest() -> None:
    points, labels = tabletop_points(np.random.default_rng(2))
    frames = cameras()
    scene = normalize(Scene(frames=frames, points=points, point_colors=np.zeros((len(points), 3), np.uint8)), NormalizeConfig())
    assert scene.capture == "unbounded" and "background" in scene.notes["capture"]
    obj = scene.points[labels == 0]
    region = np.asarray(scene.region)
    inside = np.all((obj >= region[0] - 1e-9) & (obj <= region[1] + 1e-9), axis=1)
    assert inside.mean() > 0.9
    size = region[1] - region[0]
    assert np.all(size < 1.3 * np.ptp(obj, axis=0))  # no table or room in it
    # the ground plane, carried into the normalized frame, still holds the table points
    table = scene.points[labels == 1]
    heights = table @ scene.ground[:3] - scene.ground[3]
    assert np.median(np.abs(heights)) < 0.01 * np.ptp(obj[:, 2])
    # known background (alpha or masks): the object box alone, as before
    masked = normalize(Scene(frames=cameras(), points=points, point_colors=np.zeros((len(points), 3), np.uint8),
                             has_alpha=True), NormalizeConfig())
    assert masked.capture == "object"


def test_an_object_photographed_from_one_side_is_an_object_and_a_facade_is_not() -> None:
    """Cameras on a 90° arc converge on the object but their views are too alike to count as around it: the object
    standing on the table with the room around it makes it an object capture all the same; a facade filling the
    views from the same arc stays a scene modelled whole."""
    frames = []
    for i in range(16):
        az, el = np.radians(-45 + 90 * i / 15), np.radians(25 + 10 * np.sin(3 * i))
        eye = 2.5 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), FL, FL, W / 2, H / 2, W, H))
    c2ws = np.stack([f.c2w for f in frames])
    from recon.capture.normalization import OBJECT_MAX_MEAN_VIEW, narrow_arc

    assert narrow_arc(c2ws) is not None and narrow_arc(c2ws) >= OBJECT_MAX_MEAN_VIEW  # not around it by itself
    points, labels = tabletop_points(np.random.default_rng(7))
    scene = normalize(Scene(frames=frames, points=points, point_colors=np.zeros((len(points), 3), np.uint8)),
                      NormalizeConfig())
    assert "object capture from one side" in scene.notes["capture"] and scene.region is not None
    obj = scene.points[labels == 0]
    region = np.asarray(scene.region)
    assert np.all((region[1] - region[0]) < 1.3 * np.ptp(obj, axis=0))  # the object, not the table or the room
    rng = np.random.default_rng(8)
    facade = np.column_stack([np.full(6000, -0.5) + rng.normal(0, 0.01, 6000), rng.uniform(-3, 3, (6000, 2))])
    wall = normalize(Scene(frames=frames, points=facade, point_colors=np.zeros((len(facade), 3), np.uint8)),
                     NormalizeConfig())
    assert wall.capture == "unbounded" and wall.region is None and "modelled whole" in wall.notes["capture"]


def test_ground_cut_and_region_overrides() -> None:
    scene = Scene(frames=cameras(), region=np.array([[-0.3, -0.3, -0.3], [0.3, 0.3, 0.3]]),
                  ground=np.array([0.0, 0.0, 1.0, -0.3]))
    scene.world_from_source = np.diag([2.0, 2.0, 2.0, 1.0])  # source = scene / 2
    aabb = np.array([[-1.0] * 3, [1.0] * 3])
    box, ground, why = mesh_region(scene, aabb, MeshConfig())
    np.testing.assert_allclose(box, [[-0.36, -0.36, -0.36], [0.36, 0.36, 0.36]])
    assert ground is not None and "ground plane is cut" in why
    box, ground, why = mesh_region(scene, aabb, MeshConfig(region="all"))
    np.testing.assert_allclose(box, aabb)
    assert ground is None
    box, ground, _ = mesh_region(scene, aabb, MeshConfig(region="-0.1,-0.1,-0.1,0.1,0.1,0.2", keep_ground=True))
    np.testing.assert_allclose(box, [[-0.2, -0.2, -0.2], [0.2, 0.2, 0.4]])
    assert ground is None
    with pytest.raises(ConfigError, match="mesh.region"):
        parse_region("1,2,3")
    # a ball on a table top: cutting the plane leaves the ball alone
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    table = trimesh.creation.box(extents=(2, 2, 0.05))
    table.apply_translation((0, 0, -0.3 - 0.025 + 0.02))
    both = trimesh.util.concatenate([ball, table])
    cut, removed = cut_below_plane(both, np.array([0, 0, 1.0, -0.3 + 0.02]), 0.01)
    assert removed >= len(table.faces) and cut.vertices[:, 2].min() >= -0.3 + 0.03 - 1e-9
    v, f, report = clean_mesh(both.vertices, both.faces, aabb, ground=np.array([0, 0, 1.0, -0.28]), ground_margin=0.01)
    assert report["ground_cut"]["faces_removed"] >= len(table.faces) and np.ptp(v[:, 0]) < 0.61


def wall_capture(rng: np.random.Generator) -> tuple[list[Frame], np.ndarray, np.ndarray]:
    """A head mounted on a wall (the fox): a half ball of radius 0.4 standing out of the wall x = -0.3, a picture
    frame on the wall above it (1 cm proud), cameras on a 100° arc in front. Labels: 0 object, 1 wall, 2 picture."""
    frames = []
    for i in range(12):
        az, el = np.radians(-50 + 100 * i / 11), np.radians(10 * np.sin(i))
        eye = 2.5 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), FL, FL, W / 2, H / 2, W, H))
    d = rng.normal(size=(800, 3))
    head = np.array([-0.3, 0, 0]) + 0.4 * d / np.linalg.norm(d, axis=1, keepdims=True)
    head = head[head[:, 0] > -0.3 + 0.04]
    wall = np.column_stack([np.full(4000, -0.3) + rng.normal(0, 0.003, 4000), rng.uniform(-3, 3, (4000, 2))])
    wall = wall[np.linalg.norm(wall[:, 1:], axis=1) > 0.4]  # the head hides the wall behind it
    picture = np.column_stack([np.full(300, -0.29), rng.uniform(-0.3, 0.3, 300), rng.uniform(0.55, 0.85, 300)])
    points = np.concatenate([head, wall, picture])
    return frames, points, np.repeat([0, 1, 2], [len(head), len(wall), len(picture)])


def test_an_object_on_a_wall_is_told_from_the_wall_and_the_picture_on_it() -> None:
    frames, points, labels = wall_capture(np.random.default_rng(3))
    region = region_of(points, frames)
    assert region is not None and region.ground is not None and region.ground.kind == "wall"
    np.testing.assert_allclose(region.ground.normal, [1, 0, 0], atol=0.02)  # facing the cameras
    assert abs(region.ground.offset - (-0.3)) < 0.01
    kept = labels[region.points]
    assert (kept == 0).mean() > 0.97 and region.points[labels == 0].mean() > 0.8  # the head, not wall or picture
    assert "wall" in region.reason
    # normalize carries the wall into the scene; the mesh stage cuts it and says which plane it is
    scene = normalize(Scene(frames=frames, points=points, point_colors=np.zeros((len(points), 3), np.uint8)), NormalizeConfig())
    head = scene.points[labels == 0]
    box = np.asarray(scene.region)
    assert np.all(box[1] - box[0] < 1.3 * np.ptp(head, axis=0))  # no wall or picture in the object region
    box, ground, why = mesh_region(scene, np.asarray(scene.aabb), MeshConfig())
    assert ground is not None and "wall behind the object is cut away" in why
    wall = scene.points[labels == 1]
    assert np.median(np.abs(wall @ ground[:3] - ground[3])) < 0.01 * np.ptp(head[:, 0])


def test_the_board_an_object_hangs_on_belongs_to_it_though_too_plain_to_link() -> None:
    """The mounted head, richly textured, on a dark plain board 8 cm proud of the wall and reaching 30 cm beyond the
    head, photographed from a cone in front with a longer lens that frames the head: SfM places a couple of dozen
    points on the board, too far apart to link to the head, and many photos leave them out of frame; those that most
    photos show still belong to the region and its normalized box. The picture frame on the wall stays out; so does a
    shelf as proud as the board beside it, with wall showing between; and a stray point before the head is no part of
    the mount."""
    from recon.capture.region import IN_VIEW_FRACTION, MOUNT_IN_VIEW_FRACTION, MOUNT_MIN_POINTS, in_view_fraction

    rng = np.random.default_rng(6)
    _, points, labels = wall_capture(rng)
    frames = []
    for i in range(16):
        azimuth, off_axis = 2 * np.pi * i / 16, np.radians(40) * (0.6 + 0.4 * (i % 2))
        eye = 2.5 * np.array([np.cos(off_axis), np.sin(off_axis) * np.cos(azimuth), np.sin(off_axis) * np.sin(azimuth)])
        frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), 1.8 * FL, 1.8 * FL, W / 2, H / 2, W, H))
    d = rng.normal(size=(4000, 3))
    head = np.array([-0.3, 0, 0]) + 0.4 * d / np.linalg.norm(d, axis=1, keepdims=True)
    head = head[head[:, 0] > -0.3 + 0.04]
    c2ws = np.stack([f.c2w for f in frames])
    intrinsics, sizes = np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in frames]), np.array([[f.w, f.h] for f in frames])
    around = rng.uniform(-0.75, 0.75, (3000, 2))
    around = around[(np.linalg.norm(around, axis=1) > 0.5) & (np.linalg.norm(around, axis=1) < 0.75)]
    around = np.column_stack([np.full(len(around), -0.22), around])
    shown_by = in_view_fraction(around, c2ws, intrinsics, sizes)
    board = []  # a point every 15 cm where 60-80% of the photos show the board, where more and where fewer
    for share in ((shown_by >= MOUNT_IN_VIEW_FRACTION) & (shown_by < IN_VIEW_FRACTION), shown_by >= IN_VIEW_FRACTION,
                  shown_by < MOUNT_IN_VIEW_FRACTION):
        for q in around[share]:
            if all(np.linalg.norm(q - b) > 0.15 for b in board):
                board.append(q)
    board = np.array(board)
    paper = rng.uniform(-1.5, 1.5, (12000, 2))  # wallpaper: the wall densely textured around the head
    paper = np.column_stack([np.full(len(paper), -0.3) + rng.normal(0, 0.003, len(paper)), paper])
    beside = np.column_stack([np.full(len(around), -0.22), 1.25 * around[:, 1:]])  # beyond the board's edge
    shelf = beside[(in_view_fraction(beside, c2ws, intrinsics, sizes) >= MOUNT_IN_VIEW_FRACTION)
                   & (np.linalg.norm(beside[:, 1:], axis=1) > 0.85)][:30]
    stray = np.array([[0.6, 0.0, 0.1]])  # a mistriangulated point between the head and the cameras
    points, labels = np.concatenate([points, paper]), np.concatenate([labels, np.ones(len(paper), int)])
    behind = (labels == 1) & (np.linalg.norm(points[:, 1:], axis=1) < 0.75)  # the board hides the wall behind it
    points = np.concatenate([points[~behind], head, board, stray, shelf])
    labels = np.concatenate([labels[~behind], np.zeros(len(head), int), np.full(len(board), 3), [4],
                             np.full(len(shelf), 5)])
    region = region_of(points, frames)
    assert region is not None and region.ground is not None and region.ground.kind == "wall"
    shown_by = in_view_fraction(board, c2ws, intrinsics, sizes)
    shown = shown_by >= MOUNT_IN_VIEW_FRACTION
    assert (shown_by < IN_VIEW_FRACTION)[shown].sum() >= 6 and not shown.all()
    assert np.array_equal(region.points[labels == 3], shown)  # every board point most photos show, no other one
    assert region.mount is not None and region.mount.sum() >= 6 and not region.mount[labels != 3].any()
    assert len(shelf) >= 10 and not region.points[labels == 5].any()
    assert not region.points[labels == 2].any() and (labels[region.points] == 1).mean() < 0.02
    assert "mounted on" in region.reason
    dropped = (labels == 3) & ~np.isin(np.arange(len(labels)), np.flatnonzero(region.mount)[:MOUNT_MIN_POINTS - 1])
    few = region_of(points[~dropped], frames)  # too few points for a surface: stray triangulations
    assert few is not None and few.mount is not None and not few.mount.any()
    scene = normalize(Scene(frames=frames, points=points, point_colors=np.zeros((len(points), 3), np.uint8)),
                      NormalizeConfig())
    box, held = np.asarray(scene.region), scene.points[labels == 3][shown]
    assert np.all(box[0] <= held.min(axis=0) + 1e-9) and np.all(box[1] >= held.max(axis=0) - 1e-9)
    assert np.all(box[1] - box[0] < 1.1 * np.ptp(scene.points[np.isin(labels, [0, 3])], axis=0))  # nothing more


def test_cameras_around_an_object_find_no_wall() -> None:
    # a ball with a large board standing behind it (x = -0.5), photographed from all around: the board holds plenty
    # of points outside the object, but half the cameras are behind it, so it is no wall the object hangs on
    rng = np.random.default_rng(4)
    ball, _ = tabletop_points(rng, table=False, room=False)
    board = np.column_stack([np.full(3000, -0.5) + rng.normal(0, 0.003, 3000), rng.uniform(-3, 3, (3000, 2))])
    region = region_of(np.concatenate([ball, board]), cameras())
    assert region is not None and region.ground is None


def test_the_region_holds_a_part_that_close_ups_leave_out_of_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ball with a long handle on a table in a room, photographed from a ring and from close up: the close-ups keep
    the ball in frame but not the handle's end, so too few photos show it to make the region by themselves; it is
    linked to the ball's points, so the region holds it, and still neither table nor room."""
    from recon.capture import region as object_region_module
    from recon.capture.region import in_view_fraction

    rng = np.random.default_rng(5)
    ball, labels = tabletop_points(rng)
    along = np.linspace(0.3, 0.9, 41)
    handle = np.column_stack([along, np.zeros_like(along), np.zeros_like(along)]) + rng.normal(0, 0.004, (41, 3))
    points = np.concatenate([ball, handle])
    labels = np.concatenate([labels, np.full(len(handle), 3)])
    frames = cameras() + cameras(radius=1.0)
    c2ws = np.stack([f.c2w for f in frames])
    seen = in_view_fraction(handle, c2ws, np.array([[f.fl_x, f.fl_y, f.cx, f.cy] for f in frames]),
                            np.array([[f.w, f.h] for f in frames]))
    far = handle[:, 0] > 0.75
    assert seen[far].max() < object_region_module.IN_VIEW_FRACTION  # the close-ups lose the handle's end
    region = region_of(points, frames)
    assert region is not None
    assert region.points[labels == 3].mean() > 0.95 and region.points[labels == 0].mean() > 0.8
    assert not region.points[(labels == 1) | (labels == 2)].any()
    assert "linked to them" in region.reason
    monkeypatch.setattr(object_region_module, "LINK_SPACINGS", 0.0)
    monkeypatch.setattr(object_region_module, "AIM_MAX", np.inf)  # unlinked, each point is a group of its own
    in_frame = region_of(points, frames)
    assert not in_frame.points[len(ball):][far].any()


def test_a_board_the_object_touches_joins_the_region_only_near_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ball touching a large board that stands on the table behind it (cameras all around, so the board is no wall
    the object hangs on): the board's points are linked to the ball's, but the region grows at most MAX_GROWTH of the
    in-frame region's size a side, so it does not become the board."""
    from recon.capture import region as object_region_module

    rng = np.random.default_rng(6)
    ball, _ = tabletop_points(rng, room=False)
    board = np.column_stack([np.full(12000, -0.3), rng.uniform(-6, 6, 12000), rng.uniform(TABLE_Z, 2.0, 12000)])
    points = np.concatenate([ball, board])
    region = region_of(points, cameras())
    monkeypatch.setattr(object_region_module, "LINK_SPACINGS", 0.0)
    monkeypatch.setattr(object_region_module, "AIM_MAX", np.inf)  # unlinked, each point is a group of its own
    in_frame = region_of(points, cameras())
    assert region is not None and in_frame is not None
    assert region.points.sum() > in_frame.points.sum()
    grown, before = np.ptp(points[region.points], axis=0), np.ptp(points[in_frame.points], axis=0)
    assert np.all(grown <= (1 + 2 * object_region_module.MAX_GROWTH) * before + 1e-9)
    assert grown[1] < 0.75 * np.ptp(board[:, 1])
