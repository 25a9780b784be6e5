"""The realistic tabletop capture (fixtures/gen_tabletop.py, realistic=True): its masks, lens, clutter and
exposures are what it says they are, checked against the object's mesh and the recorded camera."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image, ImageDraw
from scipy.ndimage import binary_dilation, binary_erosion

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "fixtures"))
import gen_tabletop as tt  # noqa: E402
import generate as gen  # noqa: E402

STRONG_LENS = (-0.45, 0.1)
"""Far more barrel than a real lens, so that at 128 px the distortion moves the silhouette by more than a pixel."""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 views at 96x72 with the default lens: ~1 s."""
    return tt.generate(tmp_path_factory.mktemp("tt") / "real", views=3, size="96x72", mesh_res=64, realistic=True)


@pytest.fixture(scope="module")
def distorted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tt.generate(tmp_path_factory.mktemp("tt") / "strong", views=3, size="128x96", mesh_res=64, realistic=True,
                       k1=STRONG_LENS[0], k2=STRONG_LENS[1])


def frames(out: Path) -> tuple[dict, list[tuple[np.ndarray, np.ndarray, Path]]]:
    """transforms.json and, per frame, (c2w, mask as bool, photo path)."""
    doc = json.loads((out / "transforms.json").read_text())
    rows = []
    for f in doc["frames"]:
        mask = np.asarray(Image.open(out / "masks" / (Path(f["file_path"]).stem + ".png"))) > 127
        rows.append((np.asarray(f["transform_matrix"]), mask, out / f["file_path"]))
    return doc, rows


def silhouette(mesh: trimesh.Trimesh, c2w: np.ndarray, doc: dict, k1: float, k2: float, up: int = 4) -> np.ndarray:
    """The mesh projected through an OpenCV radial camera (forward model, independent of the renderer's inverse):
    pixels it covers at least half of (triangles filled at up x up samples per pixel)."""
    w, h = doc["w"], doc["h"]
    local = (mesh.vertices - c2w[:3, 3]) @ c2w[:3, :3]
    x, y = local[:, 0] / -local[:, 2], -local[:, 1] / -local[:, 2]
    r2 = x * x + y * y
    scale = 1.0 + k1 * r2 + k2 * r2 * r2
    uv = np.stack([doc["fl_x"] * x * scale + doc["cx"], doc["fl_y"] * y * scale + doc["cy"]], axis=-1) * up
    img = Image.new("L", (w * up, h * up), 0)
    draw = ImageDraw.Draw(img)
    for tri in uv[mesh.faces]:
        draw.polygon([tuple(p) for p in tri], fill=255)
    return np.asarray(img, dtype=np.float32).reshape(h, up, w, up).mean(axis=(1, 3)) >= 127.5


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_lens_undistort_inverts_distort_and_folding_lenses_are_refused() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.6, 0.6, 1000), rng.uniform(-0.45, 0.45, 1000)
    for lens in (tt.Lens(tt.LENS_K1, tt.LENS_K2), tt.Lens(*STRONG_LENS)):
        back = lens.undistort(*lens.distort(x, y))
        assert np.abs(np.stack(back) - np.stack([x, y])).max() < 1e-9
    tt.Lens(*STRONG_LENS).check(0.6)
    with pytest.raises(ValueError, match="folds over"):
        tt.Lens(-0.6, 0.08).check(0.6)  # its distorted radius peaks at 0.52


def test_pixel_rays_reproject_to_their_pixels_through_the_recorded_lens() -> None:
    """A point on the ray through pixel (u, v), projected by OpenCV's model with the same k1/k2, lands on (u, v)."""
    k = gen.default_intrinsics(160, 120, fov_x_deg=50.0)
    lens = tt.Lens(*STRONG_LENS)
    c2w = gen.look_at(np.array([2.0, -1.0, 1.5]), np.zeros(3))
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 160, 500), rng.uniform(0, 120, 500)
    points = c2w[:3, 3] + 3.0 * tt.pixel_rays(c2w, k, lens, u, v)
    local = (points - c2w[:3, 3]) @ c2w[:3, :3]
    xd, yd = lens.distort(local[:, 0] / -local[:, 2], -local[:, 1] / -local[:, 2])
    assert np.abs(k.fl_x * xd + k.cx - u).max() < 1e-3 and np.abs(k.fl_y * yd + k.cy - v).max() < 1e-3
    assert np.abs(k.fl_x * local[:, 0] / -local[:, 2] + k.cx - u).max() > 3.0  # a pinhole puts them elsewhere


def test_masks_are_the_object_silhouette_through_the_distorted_lens(distorted: Path) -> None:
    doc, rows = frames(distorted)
    assert (doc["k1"], doc["k2"]) == STRONG_LENS  # the true camera is recorded
    mesh = trimesh.load(distorted / "gt_mesh.ply")
    for c2w, mask, _ in rows:
        true_lens = silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])
        pinhole = silhouette(mesh, c2w, doc, 0.0, 0.0)
        assert iou(mask, true_lens) > 0.975
        assert iou(mask, true_lens) > iou(mask, pinhole) + 0.005  # the distortion is in the masks, not only the photos
        assert abs(mask.sum() / true_lens.sum() - 1) < 0.012 < abs(mask.sum() / pinhole.sum() - 1)


def test_default_lens_mesh_reprojects_onto_masks_and_clutter_stays_outside(capture: Path) -> None:
    doc, rows = frames(capture)
    info = json.loads((capture / "scene_info.json").read_text())
    mesh = trimesh.load(capture / "gt_mesh.ply")
    room = tt.Room()
    k = gen.default_intrinsics(doc["w"], doc["h"], fov_x_deg=50.0)
    lens = tt.Lens(doc["k1"], doc["k2"])
    seen_on_table = seen_in_room = 0
    for (c2w, mask, _), photo in zip(rows, info["photos"]):
        assert iou(mask, silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])) > 0.95
        assert photo["object_pixels_hidden_by_clutter"] == 0
        rays = tt.pixel_rays(c2w, k, lens, *pixel_centres(doc))
        labels = tt.trace(room, c2w[:3, 3], rays, list(range(len(room.props))), 0.0)[1].reshape(mask.shape)
        clutter = labels >= 1  # 0 is the table itself
        assert not (binary_erosion(mask) & clutter).any()  # only the object's anti-aliased rim may show some behind it
        assert ((labels == tt.OBJECT) == mask).mean() > 0.98  # the object, and nothing else, is what the mask covers
        on_table = np.isin(labels, [i for i, p in enumerate(room.props) if p.on_table])
        seen_on_table += int(on_table.sum())
        seen_in_room += int((clutter & ~on_table).sum())
    assert seen_on_table > 20 and seen_in_room > 20  # clutter on the table and in the room is in the photos


def pixel_centres(doc: dict) -> tuple[np.ndarray, np.ndarray]:
    jj, ii = np.mgrid[0:doc["h"], 0:doc["w"]]
    return ii.ravel() + 0.5, jj.ravel() + 0.5


def test_photos_are_auto_exposed_white_balanced_and_carry_camera_exif(capture: Path) -> None:
    doc, rows = frames(capture)
    info = json.loads((capture / "scene_info.json").read_text())
    exposures = [p["exposure"] for p in info["photos"]]
    assert max(exposures) / min(exposures) > 1.05  # each photo metered on its own
    assert len({tuple(p["white_balance"]) for p in info["photos"]}) == len(rows)
    assert len({p["blur_sigma_px"] for p in info["photos"]}) == len(rows)
    for _, _, path in rows:
        photo = np.asarray(Image.open(path), dtype=np.float32) / 255
        assert abs(photo.mean() - tt.METER_TARGET) < 0.12  # the meter brought every frame near its target
        with Image.open(path) as img:
            sub = img.getexif().get_ifd(0x8769)
        assert abs(sub[0xA405] * np.hypot(doc["w"], doc["h"]) / np.hypot(36, 24) / doc["fl_x"] - 1) < 0.03
    assert info["gains"][0] == pytest.approx(np.multiply(exposures[0], info["photos"][0]["white_balance"]).tolist())


def test_closeups_crop_the_object_and_their_masks_stay_true(tmp_path: Path) -> None:
    """With closeups every second photo steps in on one part of the object: its mask runs off the frame, the far end
    of the object leaves the frame in most close-ups (what the fox's close-ups do to its ears), and the masks are
    still the object's silhouette; the orbit's photos keep the whole object in frame."""
    from recon.capture.region import in_view_fraction

    out = tt.generate(tmp_path / "cu", views=8, size="96x72", mesh_res=64, realistic=True, closeups=True)
    doc, rows = frames(out)
    info = json.loads((out / "scene_info.json").read_text())
    assert info["closeups"] == [1, 3, 5, 7]
    mesh = trimesh.load(out / "gt_mesh.ply")
    for i, (c2w, mask, _) in enumerate(rows):
        border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
        assert border.any() == (i in info["closeups"]), i
        assert iou(mask, silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])) > 0.95
    cover = [mask.mean() for _, mask, _ in rows]
    assert min(cover[1::2]) > 3 * max(cover[0::2])
    close = np.array([rows[i][0] for i in info["closeups"]])
    intrinsics = np.tile([doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"]], (len(close), 1))
    sizes = np.tile([doc["w"], doc["h"]], (len(close), 1))
    points, _ = trimesh.sample.sample_surface(mesh, 2000, seed=0)
    assert np.mean(in_view_fraction(points, close, intrinsics, sizes) <= 0.5) > 0.2
    with pytest.raises(ValueError, match="closeups"):
        tt.generate(tmp_path / "no", views=2, size="32x24", realistic=True, turntable=True, closeups=True)


def test_far_photos_hold_the_object_small_and_its_masks_stay_true(tmp_path: Path, capture: Path) -> None:
    """far: the same capture from FAR_FRAMING / REAL_FRAMING times as far, so the object covers about that squared
    less of each photo, its masks still its silhouette; with a turntable or close-ups it is refused."""
    out = tt.generate(tmp_path / "far", views=3, size="96x72", mesh_res=64, realistic=True, far=True)
    doc, rows = frames(out)
    mesh = trimesh.load(out / "gt_mesh.ply")
    for c2w, mask, _ in rows:
        assert not np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).any()  # all of it in frame
        assert iou(mask, silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])) > 0.9
    near = np.mean([mask.mean() for _, mask, _ in frames(capture)[1]])
    ratio = near / np.mean([mask.mean() for _, mask, _ in rows])
    assert 0.5 * (tt.FAR_FRAMING / tt.REAL_FRAMING) ** 2 < ratio < 2 * (tt.FAR_FRAMING / tt.REAL_FRAMING) ** 2
    with pytest.raises(ValueError, match="far"):
        tt.generate(tmp_path / "no", views=2, size="32x24", realistic=True, closeups=True, far=True)


def test_an_arc_keeps_the_photos_on_the_objects_front_and_is_refused_where_it_means_nothing(tmp_path: Path) -> None:
    """arc: the hand-held photos' azimuths within an arc that wide around +X (the golden-ratio spread fills it), the
    object in the middle of each; with a turntable or on a wall it is refused."""
    world = tt.Tabletop()
    cams = tt.poses(24, world, 5.0, 0, tt.REAL_ELEVATION_DEG, tt.REAL_LOOK_JITTER, tt.REAL_ROLL_DEG, arc_deg=90.0)
    offset = cams[:, :3, 3] - world.center
    azimuth = np.degrees(np.arctan2(offset[:, 1], offset[:, 0]))
    assert np.abs(azimuth).max() <= 45 + 4 and np.ptp(azimuth) > 80
    around = tt.poses(24, world, 5.0, 0, tt.REAL_ELEVATION_DEG, tt.REAL_LOOK_JITTER, tt.REAL_ROLL_DEG)
    offset = around[:, :3, 3] - world.center
    assert np.abs(np.degrees(np.arctan2(offset[:, 1], offset[:, 0]))).max() > 150  # without an arc: all around
    for kwargs in ({"turntable": True}, {"mounted": True}, {}):
        with pytest.raises(ValueError, match="arc"):
            tt.generate(tmp_path / "no", views=2, size="32x24", realistic=bool(kwargs), arc=90.0, **kwargs)


@pytest.mark.parametrize("shape", ["thin", "concave", "hole", "pieces"])
def test_another_object_stands_on_the_table_and_its_masks_are_its_silhouette(tmp_path: Path, shape: str) -> None:
    """shape: another of generate.py's objects in the blocks' place, sunk TABLE_SINK into the table top as they are,
    its true mesh above the table, its masks its silhouette; a name generate.py lacks is refused."""
    out = tt.generate(tmp_path / shape, views=2, size="96x72", mesh_res=64, realistic=True, shape=shape)
    info = json.loads((out / "scene_info.json").read_text())
    doc, rows = frames(out)
    mesh = trimesh.load(out / "gt_mesh.ply")
    assert info["object"] == shape and shape in info["description"]
    assert abs(mesh.bounds[0, 2] - info["table_z"]) < 0.03  # it stands on the table, not above or in it
    blocks = trimesh.load(tt.generate(tmp_path / "blocks", views=1, size="32x24", mesh_res=64) / "gt_mesh.ply")
    assert not np.allclose(mesh.bounds, blocks.bounds, atol=0.02)  # another object, not the blocks again
    for c2w, mask, _ in rows:
        assert iou(mask, silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])) > 0.85
    with pytest.raises(ValueError, match="unknown object"):
        tt.generate(tmp_path / "no", views=2, size="32x24", realistic=True, shape="teapot")


def test_a_painted_object_has_the_same_shape_in_a_few_flat_colours_with_few_features(tmp_path: Path) -> None:
    """painted changes the object's albedo alone: the same masks, pixels near the palette's colours, and under a
    third of the SIFT features the richly textured object gives inside its masks (the room is the same)."""
    import cv2

    def capture(painted: bool) -> list[tuple[np.ndarray, np.ndarray]]:
        out = tt.generate(tmp_path / str(painted), views=2, size="320x240", mesh_res=64, realistic=True,
                          painted=painted)
        return [(np.asarray(Image.open(path).convert("L")), mask) for _, mask, path in frames(out)[1]]

    textured, painted = capture(False), capture(True)
    sift = cv2.SIFT_create()
    counts = {}
    for name, views in (("textured", textured), ("painted", painted)):
        counts[name] = 0
        for gray, mask in views:
            inside = binary_erosion(mask, iterations=3).astype(np.uint8) * 255
            counts[name] += len(sift.detect(gray, inside))
    assert [m.tolist() for _, m in textured] == [m.tolist() for _, m in painted]
    assert counts["painted"] < counts["textured"] / 3, counts
    palette = np.asarray(tt.PAINT, np.float32)
    albedo = tt.painted_albedo(np.random.default_rng(0).uniform(-1, 1, (4000, 3)).astype(np.float32),
                               gen.noise_table(0))
    nearest = np.min(np.linalg.norm(albedo[:, None] - palette[None], axis=2), axis=1)
    assert np.mean(nearest < 0.05) > 0.8  # flat paint, the edges between colours aside
    with pytest.raises(ValueError, match="painted"):
        tt.generate(tmp_path / "no", views=2, size="32x24", painted=True)


def test_mounted_photos_face_the_wall_level_with_its_up(tmp_path: Path) -> None:
    """With mounted the table top is a wall: every camera is in front of it within the cone, held level with the
    wall's up (+Y) up to the hand's roll, and the masks are still the object's silhouette."""
    out = tt.generate(tmp_path / "mt", views=6, size="96x72", mesh_res=64, realistic=True, mounted=True)
    doc, rows = frames(out)
    info = json.loads((out / "scene_info.json").read_text())
    center, up = np.asarray(info["object_center"]), np.asarray(tt.MOUNT_UP)
    assert info["world_up"] == list(tt.MOUNT_UP)
    mesh = trimesh.load(out / "gt_mesh.ply")
    tilts = []
    for c2w, mask, _ in rows:
        away = c2w[:3, 3] - center
        tilts.append(np.degrees(np.arccos(away[2] / np.linalg.norm(away))))
        assert abs(c2w[:3, 0] @ up) < np.sin(np.radians(tt.REAL_ROLL_DEG + 1))  # level with the wall's up
        assert c2w[:3, 1] @ up > 0.4  # the photo's top is the wall's top
        assert iou(mask, silhouette(mesh, c2w, doc, doc["k1"], doc["k2"])) > 0.95
    assert max(tilts) < tt.MOUNT_CONE_DEG + 5 and max(tilts) - min(tilts) > 25  # in front, from spread directions


def test_a_mounted_object_hangs_on_paper_of_its_own_hues_and_casts_a_soft_shadow() -> None:
    """The mounted capture's wall is papered in flowers coloured like the object (a wooden table's colours are far
    from them), and its light is broad: the object's shadow on the wall has a penumbra of points that see part of
    the light, as much shadow in all as a point light casts, where the point light's shadow has none. The object
    hangs on a board that is part of it (it reaches past the object's extent on the wall)."""
    table, soft, hard = tt.Room(), tt.Room(mounted=True), tt.Room(mounted=True)
    hard.light_spread_deg = 0.0
    for room in (table, soft, hard):
        room.textures(0)
    wall = soft.props[0]
    cx, cy, _ = soft.top.center
    xx, yy = np.meshgrid(np.linspace(cx - 1.5, cx + 1.5, 80), np.linspace(cy - 1.5, cy + 1.5, 80))
    grid = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, wall.center[2] + wall.size[2] + tt.SHADOW_BIAS)],
                    axis=1).astype(np.float32)
    under_board = soft.top.object_sdf(grid) < 0
    assert under_board.mean() > 0.05 and (table.top.object_sdf(grid) < 0).mean() < 0.5 * under_board.mean()
    grid[under_board, 2] = soft.top.table_z + tt.MOUNT_BOARD[2] + tt.SHADOW_BIAS  # on the board's face
    on_wall = grid[soft.top.object_sdf(grid) > 0]  # the wall and the board around the object
    point, broad = tt.light_seen(hard, on_wall), tt.light_seen(soft, on_wall)
    assert set(np.unique(point)) == {0.0, 1.0}
    assert ((broad > 0) & (broad < 1)).mean() > 0.01 and (broad == 0).mean() > 0.01  # a penumbra round an umbra
    assert abs(broad.mean() - point.mean()) < 0.2 * (1 - point.mean())
    dirs = tt.light_directions(on_wall[:50], tt.MOUNT_LIGHT_DEG)
    assert dirs.shape == (tt.SOFT_SHADOW_RAYS, 50, 3)
    assert np.degrees(np.arccos(np.clip(dirs @ gen.LIGHT_DIR.astype(np.float32), -1, 1))).max() < tt.MOUNT_LIGHT_DEG
    rng = np.random.default_rng(0)
    lo, hi = table.top.object_aabb
    object_colours = gen.albedo((lo + rng.random((1500, 3)) * (hi - lo)).astype(np.float32), soft.tables["object"])

    def nearest_wall_colour(room: tt.Room) -> float:
        colours = room.props[0].albedo(on_wall[rng.choice(len(on_wall), 1500)], room.tables["prop0"])
        return float(np.median(np.linalg.norm(object_colours[:, None] - colours[None], axis=2).min(axis=1)))

    assert nearest_wall_colour(soft) < 0.5 * nearest_wall_colour(table)


def test_bench_dataset_is_the_photos_alone_with_the_truth_beside(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`recon bench --data tabletop_realistic` gets a photos folder with no masks anywhere recon looks for them, and
    compare_to_gt finds the true poses next to the true mesh."""
    from recon.app.bench import resolve_dataset
    from recon.capture.scene import find_masks

    monkeypatch.setattr(tt, "BENCH_CAPTURE", {"views": 3, "size": "64x48", "seed": 0, "supersample": 1, "mesh_res": 48})
    monkeypatch.setitem(sys.modules, "_recon_fixture_gen_tabletop", tt)  # the module bench loads, with the tiny size
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    photos, gt = resolve_dataset("tabletop_realistic")
    assert photos == tmp_path / "recon" / "datasets" / "tabletop_realistic" / "photos"
    listed = sorted(photos.iterdir())
    assert [p.name for p in listed] == ["view_000.jpg", "view_001.jpg", "view_002.jpg"]
    assert find_masks(listed) == (None, {})
    assert gt.is_file() and (gt.parent / "transforms.json").is_file() and (gt.parent / "masks").is_dir()
    inode = listed[0].stat().st_ino
    tt.bench_dataset(photos.parent, verbose=False)  # cached: nothing rendered or linked again
    assert listed[0].stat().st_ino == inode


def test_bench_dataset_at_a_seed_is_another_draw(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--data tabletop_realistic@SEED` renders the capture from that seed into its own cache folder: other cameras
    than the default draw's; a seed that is not a whole number is refused naming the data set."""
    import json

    from recon.app.bench import resolve_dataset
    from recon.errors import ReconError

    monkeypatch.setattr(tt, "BENCH_CAPTURE", {"views": 3, "size": "64x48", "seed": 0, "supersample": 1, "mesh_res": 48})
    monkeypatch.setitem(sys.modules, "_recon_fixture_gen_tabletop", tt)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    default_photos, default_gt = resolve_dataset("tabletop_realistic")
    photos, gt = resolve_dataset("tabletop_realistic@5")
    assert photos == tmp_path / "recon" / "datasets" / "tabletop_realistic@5" / "photos"
    assert len(list(photos.iterdir())) == 3

    def centres(gt_mesh: Path) -> np.ndarray:
        frames = json.loads((gt_mesh.parent / "transforms.json").read_text())["frames"]
        return np.array([np.array(f["transform_matrix"])[:3, 3] for f in frames])

    assert not np.allclose(centres(gt), centres(default_gt))
    with pytest.raises(ReconError, match="tabletop_realistic@two"):
        resolve_dataset("tabletop_realistic@two")


def test_a_plain_table_gives_sift_next_to_nothing_beside_the_object(tmp_path: Path) -> None:
    """table="plain" changes the table top's albedo alone: the same masks, and under a fifth of the SIFT features the
    wooden top gives in the lower half of the photos, outside the object's masks (the table, and the same clutter)."""
    import cv2

    def capture(table: str) -> list[tuple[np.ndarray, np.ndarray]]:
        out = tt.generate(tmp_path / table, views=2, size="320x240", mesh_res=64, realistic=True, table=table)
        return [(np.asarray(Image.open(path).convert("L")), mask) for _, mask, path in frames(out)[1]]

    wood, plain = capture("wood"), capture("plain")
    sift = cv2.SIFT_create()
    counts = {}
    for name, views in (("wood", wood), ("plain", plain)):
        counts[name] = 0
        for gray, mask in views:
            beside = ~binary_dilation(mask, iterations=4)
            beside[: mask.shape[0] // 2] = False
            counts[name] += len(sift.detect(gray, beside.astype(np.uint8) * 255))
    assert [m.tolist() for _, m in wood] == [m.tolist() for _, m in plain]
    assert counts["plain"] < counts["wood"] / 5, counts
    with pytest.raises(ValueError, match="plain"):
        tt.generate(tmp_path / "no", views=2, size="32x24", table="plain")


def test_a_dark_object_has_the_same_masks_and_a_fifth_of_the_light(tmp_path: Path) -> None:
    """dark scales the object's albedo alone (`DARK_ALBEDO`): the same masks, and inside them the photos are far
    darker than the textured object's (the exposure is the same: the room fills most of the frame)."""
    def capture(dark: bool) -> list[tuple[np.ndarray, np.ndarray]]:
        out = tt.generate(tmp_path / str(dark), views=2, size="160x120", mesh_res=64, realistic=True, dark=dark)
        return [(np.asarray(Image.open(path).convert("L"), np.float32), mask) for _, mask, path in frames(out)[1]]

    light, dark = capture(False), capture(True)
    assert [m.tolist() for _, m in light] == [m.tolist() for _, m in dark]
    inside = [binary_erosion(m, iterations=2) for _, m in light]
    ratio = np.mean([d[k].mean() / l[k].mean() for (l, _), (d, _), k in zip(light, dark, inside)])
    assert ratio < 0.45, ratio
    with pytest.raises(ValueError, match="dark"):
        tt.generate(tmp_path / "no", views=2, size="32x24", dark=True)
