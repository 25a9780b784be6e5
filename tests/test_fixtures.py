"""The synthetic capture generator (fixtures/generate.py) and the shipped sample (fixtures/sample/).

The generator is the ground truth for later pipeline tests, so its own pieces are checked against
closed forms (SDF distances, ray-sphere hits, a sphere's volume) and its captures against
themselves: the true mesh, seen through each frame's pose and intrinsics, must cover exactly the
non-white pixels of that frame's photo.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.ndimage import binary_closing

from tests.scripts import load_script

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "fixtures" / "sample"


gen = load_script("fixtures/generate.py", "fixtures_generate")
TINY = dict(views=6, size=64, seed=3, mesh_res=96)


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory) -> Path:
    """6 views at 64 px of the default scene (~2 s)."""
    return gen.generate(tmp_path_factory.mktemp("tiny"), **TINY)


# ---------------------------------------------------------------------------------------------
# helpers: project a capture's true mesh into its photos
# ---------------------------------------------------------------------------------------------
def _load(capture: Path):
    meta = json.loads((capture / "transforms.json").read_text())
    mesh = trimesh.load(capture / "gt_mesh.ply", process=False)
    return meta, mesh


def _project(points: np.ndarray, c2w: np.ndarray, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixel coords (N, 2) (x right, y down) and depth (N,), OpenGL c2w."""
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera axes (rows times R = R^T p)
    depth = -cam[:, 2]
    u = meta["cx"] + meta["fl_x"] * cam[:, 0] / depth
    v = meta["cy"] - meta["fl_y"] * cam[:, 1] / depth
    return np.stack([u, v], axis=-1), depth


def _object_mask(capture: Path, frame: dict) -> np.ndarray:
    """(h, w) bool: pixels of the photo that are clearly not the white background."""
    img = np.asarray(Image.open(capture / frame["file_path"]).convert("RGB"), dtype=np.float32) / 255
    return img.min(axis=-1) < 0.9


def _silhouette_iou(mask: np.ndarray, samples: np.ndarray, c2w: np.ndarray, meta: dict) -> float:
    """IoU of the photo's object mask and the pixels hit by projected surface samples."""
    uv, depth = _project(samples, c2w, meta)
    h, w = mask.shape
    ij = np.floor(uv).astype(int)
    ok = (depth > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    splat = np.zeros_like(mask)
    splat[ij[ok, 1], ij[ok, 0]] = True
    splat = binary_closing(splat, border_value=0)  # fill pixels the random samples missed
    return float((splat & mask).sum() / (splat | mask).sum())


def _check_projection(capture: Path, frame_ids, n_samples: int) -> None:
    meta, mesh = _load(capture)
    samples, _ = trimesh.sample.sample_surface_even(mesh, n_samples, seed=0)
    samples = np.asarray(samples)
    for i in frame_ids:
        frame = meta["frames"][i]
        c2w = np.array(frame["transform_matrix"])
        mask = _object_mask(capture, frame)
        # every vertex lands inside the image, on the object (an occluded vertex still lands on
        # the object in front of it); silhouette edges are anti-aliased, so allow a sliver
        uv, depth = _project(np.asarray(mesh.vertices), c2w, meta)
        assert np.all(depth > 0)
        assert np.all((uv >= 0) & (uv < [meta["w"], meta["h"]]))
        ij = np.floor(uv).astype(int)
        on_object = mask[ij[:, 1], ij[:, 0]].mean()
        assert on_object > 0.995, f"frame {i}: only {on_object:.1%} of the mesh projects onto the object"
        iou = _silhouette_iou(mask, samples, c2w, meta)
        assert iou > 0.95, f"frame {i}: silhouette IoU {iou:.3f}"
        # the check has teeth: the same mesh seen from a camera moved by 5% of its distance
        moved = c2w.copy()
        moved[:3, 3] += 0.05 * np.linalg.norm(c2w[:3, 3] - mesh.bounds.mean(axis=0)) * c2w[:3, 0]
        assert _silhouette_iou(mask, samples, moved, meta) < iou - 0.1


# ---------------------------------------------------------------------------------------------
# pieces against closed forms
# ---------------------------------------------------------------------------------------------
def test_primitives_match_closed_form_distances():
    p = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.5, 3.0]])
    np.testing.assert_allclose(gen.sd_sphere(p, (0, 0, 0), 1.0), [1.0, -1.0, math.sqrt(9.5) - 1.0])
    box = gen.sd_round_box(p, (0, 0, 0), (1.0, 1.0, 1.0), 0.0)
    np.testing.assert_allclose(box, [1.0, -1.0, 2.0])
    # rounding keeps the outer size: the face centre stays on the surface
    np.testing.assert_allclose(gen.sd_round_box(np.array([[1.0, 0, 0]]), (0, 0, 0), (1, 1, 1), 0.2), [0.0], atol=1e-12)
    # torus (ring of radius 0.6 in XY, tube 0.1): centre is 0.5 away, on-ring point is inside by 0.1
    torus = gen.sd_torus(np.array([[0.0, 0, 0], [0.6, 0, 0], [0, 0, 1.0]]), (0, 0, 0), 0.6, 0.1)
    np.testing.assert_allclose(torus, [0.5, -0.1, math.hypot(0.6, 1.0) - 0.1])
    # a rotated torus: its ring now lies in the XZ plane
    tilted = gen.sd_torus(np.array([[0.0, 0, 0.6]]), (0, 0, 0), 0.6, 0.1, gen.rotation(rx_deg=90))
    np.testing.assert_allclose(tilted, [-0.1], atol=1e-12)
    cap = gen.sd_capsule(np.array([[0.5, 0, 0], [0, 0, 2.0]]), (0, 0, -1), (0, 0, 1), 0.1)
    np.testing.assert_allclose(cap, [0.4, 0.9])
    cyl = gen.sd_cylinder(np.array([[0.0, 0, 0], [2.0, 0, 0], [0, 0, 3.0]]), (0, 0, 0), 1.0, 2.0)
    np.testing.assert_allclose(cyl, [-1.0, 1.0, 1.0])


def test_primitives_keep_float32():
    p = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float32)
    for name in gen.SCENES:
        assert gen.scene_sdf(name)(p).dtype == np.float32, name


def test_sphere_trace_hits_sphere_at_closed_form_distance():
    rng = np.random.default_rng(1)
    center, r = np.array([0.2, -0.1, 0.3]), 0.5
    sdf = lambda p: gen.sd_sphere(p, center, r)  # noqa: E731
    origins = center + rng.normal(size=(500, 3)) * 0.1 + np.array([0.0, 0.0, 3.0])
    targets = center + rng.uniform(-0.8, 0.8, size=(500, 3))
    dirs = targets - origins
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    # closed form: |o + t d - c| = r
    oc = origins - center
    b = np.sum(oc * dirs, axis=-1)
    disc = b * b - (np.sum(oc * oc, axis=-1) - r * r)
    aabb = np.stack([center - r, center + r])
    t0, t1 = gen.ray_aabb(origins, dirs, aabb)
    t, hit = gen.sphere_trace(sdf, origins, dirs, t0, t1)
    clear = np.abs(disc) > 1e-3  # leave out rays that graze the sphere
    np.testing.assert_array_equal(hit[clear], disc[clear] > 0)
    hits = hit & clear
    assert hits.sum() > 100
    t_true = -b[hits] + -np.sqrt(disc[hits])
    # tracing stops once the distance is below eps (2e-4), never past the surface: it stops short
    # by at most eps / cos(incidence), and for a sphere cos(incidence) = sqrt(disc) / r
    short = t_true - t[hits]
    assert short.min() > -1e-5
    assert np.all(short <= 2e-4 * r / np.sqrt(disc[hits]) + 1e-5)


def test_sphere_trace_cone_catches_grazing_rays():
    # a slab's top face at z = 0; rays start 0.01 above it and descend at 0.5 degrees
    sdf = lambda p: gen.sd_round_box(p, (0, 0, -0.5), (50.0, 50.0, 0.5), 0.0)  # noqa: E731
    n = 16
    origins = np.stack([np.zeros(n), np.linspace(-0.1, 0.1, n), np.full(n, 0.01)], axis=-1)
    a = math.radians(0.5)
    dirs = np.tile([math.cos(a), 0.0, -math.sin(a)], (n, 1))
    t_near, t_far = np.zeros(n), np.full(n, 10.0)
    _, hit_plain = gen.sphere_trace(sdf, origins, dirs, t_near, t_far)
    assert not hit_plain.any()  # the plain criterion runs out of steps: it would eat silhouettes
    cone = 2e-3
    t, hit = gen.sphere_trace(sdf, origins, dirs, t_near, t_far, cone=cone)
    assert hit.all()
    p = origins + t[:, None] * dirs
    assert np.all(np.abs(sdf(p)) < 2e-4 + cone * t)  # the hit is within the ray's footprint
    assert np.all(t < 0.01 / math.sin(a) + 1e-3)  # and never past the true crossing


def test_camera_rays_follow_the_pinhole_model():
    k = gen.Intrinsics(fl_x=50.0, fl_y=60.0, cx=16.0, cy=12.0, w=32, h=24)
    c2w = gen.look_at(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.5]))
    origin, dirs = gen.camera_rays(c2w, k, ss=1)
    assert dirs.shape == (32 * 24, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(origin, c2w[:3, 3])
    # pixel (i=3, j=5) has its centre at (3.5, 5.5): back into the camera frame and the image
    d_cam = dirs[5 * 32 + 3] @ c2w[:3, :3]
    assert d_cam[2] < 0  # OpenGL: the camera looks down -Z
    np.testing.assert_allclose(16.0 + 50.0 * d_cam[0] / -d_cam[2], 3.5, atol=1e-4)
    np.testing.assert_allclose(12.0 - 60.0 * d_cam[1] / -d_cam[2], 5.5, atol=1e-4)
    # supersamples of one pixel average to the pixel centre's direction
    _, sub = gen.camera_rays(c2w, k, ss=2)
    mean = sub.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3))[5, 3]
    np.testing.assert_allclose(mean / np.linalg.norm(mean), dirs[5 * 32 + 3], atol=1e-4)


def test_orbit_poses_look_at_the_object_from_the_band():
    center = np.array([0.3, -0.2, 0.1])
    poses = gen.orbit_poses(40, center, 2.0, seed=0)
    elev = np.degrees(np.arcsin((poses[:, 2, 3] - center[2]) / np.linalg.norm(poses[:, :3, 3] - center, axis=-1)))
    lo, hi = gen.ELEVATION_RANGE_DEG
    assert elev.min() > lo - 5 and elev.max() < hi + 5 and elev.max() - elev.min() > 0.8 * (hi - lo)
    to_center = center - poses[:, :3, 3]
    to_center /= np.linalg.norm(to_center, axis=-1, keepdims=True)
    cos = np.sum(-poses[:, :3, 2] * to_center, axis=-1)  # -Z is the viewing direction
    assert cos.min() > math.cos(math.radians(5))
    np.testing.assert_allclose(poses[:, 2, 0], 0.0, atol=1e-12)  # no roll: +X stays horizontal
    assert np.all(poses[:, 2, 1] > 0)  # +Y points up-ish


def test_gt_mesh_of_a_sphere_has_the_closed_form_volume():
    center, r = np.array([0.3, -0.2, 0.1]), 0.5
    sdf = lambda p: gen.sd_sphere(p, center, r)  # noqa: E731
    mesh = gen.gt_mesh(sdf, gen.sdf_bounds(sdf), res=64, max_faces=None)
    assert mesh.is_watertight and mesh.euler_number == 2
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * r**3, rel=5e-3)  # > 0: outward winding
    np.testing.assert_allclose(mesh.center_mass, center, atol=1e-3)
    assert gen.surface_error(sdf, mesh, n=20_000)["max"] < 1e-3


@pytest.mark.parametrize("scene, genus", [("blocks", 1), ("thin", 0), ("concave", 0), ("hole", 2)])
def test_scenes_are_unit_sized_off_centre_single_bodies(scene, genus):
    sdf = gen.scene_sdf(scene)
    mesh = gen.gt_mesh(sdf, gen.sdf_bounds(sdf), res=96, max_faces=None)
    assert mesh.is_watertight
    assert len(mesh.split(only_watertight=False)) == 1
    assert mesh.euler_number == 2 - 2 * genus
    assert 0.6 < mesh.extents.max() < 1.5
    assert np.linalg.norm(mesh.bounds.mean(axis=0)) > 0.2  # normalization must have work to do


def test_unknown_scene_is_refused():
    with pytest.raises(ValueError, match="unknown scene"):
        gen.scene_sdf("teapot")


# ---------------------------------------------------------------------------------------------
# a whole (tiny) capture
# ---------------------------------------------------------------------------------------------
def test_capture_files_and_keys(tiny_capture):
    meta = json.loads((tiny_capture / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", "camera_model", "frames"):
        assert key in meta, key
    assert meta["camera_model"] == "OPENCV"
    assert (meta["w"], meta["h"]) == (64, 64) and (meta["cx"], meta["cy"]) == (32.0, 32.0)
    assert [meta[k] for k in ("k1", "k2", "p1", "p2")] == [0.0] * 4
    fov = math.degrees(2 * math.atan(meta["w"] / (2 * meta["fl_x"])))
    assert 40 <= fov <= 50
    assert len(meta["frames"]) == 6
    for i, frame in enumerate(meta["frames"]):
        assert frame["file_path"] == f"images/view_{i:03d}.jpg"
        with Image.open(tiny_capture / frame["file_path"]) as img:
            assert img.format == "JPEG" and img.mode == "RGB" and img.size == (64, 64)
    info = json.loads((tiny_capture / "scene_info.json").read_text())
    assert (info["scene"], info["seed"], info["views"], info["w"], info["h"]) == ("blocks", 3, 6, 64, 64)
    bounds = np.array(info["object_bounds"])
    mesh = trimesh.load(tiny_capture / "gt_mesh.ply", process=False)
    np.testing.assert_allclose(mesh.bounds, bounds, atol=1e-6)


def test_capture_poses_are_rigid_opengl_c2w(tiny_capture):
    meta, mesh = _load(tiny_capture)
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
        r = c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)
        # the object's centre is in front of the camera (-Z) and near the image centre
        (uv,), (depth,) = _project(mesh.bounds.mean(axis=0)[None], c2w, meta)
        assert depth > mesh.extents.max()
        assert np.all(np.abs(uv - [meta["cx"], meta["cy"]]) < 0.15 * meta["w"])


def test_capture_gt_mesh_projects_onto_the_photos(tiny_capture):
    _check_projection(tiny_capture, range(6), n_samples=20_000)


def test_capture_background_is_white_and_object_textured(tiny_capture):
    meta, _ = _load(tiny_capture)
    frame = meta["frames"][0]
    img = np.asarray(Image.open(tiny_capture / frame["file_path"]), dtype=np.float32) / 255
    mask = _object_mask(tiny_capture, frame)
    assert 0.1 < mask.mean() < 0.8
    assert img[0].min() > 0.97 and img[:, 0].min() > 0.97  # border rows/columns: background
    obj = img[mask]
    assert obj.std(axis=0).min() > 0.1  # colorful: every channel varies across the object


def test_capture_is_deterministic_for_a_seed(tiny_capture, tmp_path):
    again = gen.generate(tmp_path / "again", **TINY)
    for rel in ["transforms.json", "scene_info.json", "images/view_000.jpg", "images/view_005.jpg"]:
        assert (again / rel).read_bytes() == (tiny_capture / rel).read_bytes(), rel
    other = gen.generate(tmp_path / "other", **{**TINY, "seed": 4, "views": 2})
    a = json.loads((tiny_capture / "transforms.json").read_text())["frames"][0]["transform_matrix"]
    b = json.loads((other / "transforms.json").read_text())["frames"][0]["transform_matrix"]
    assert not np.allclose(a, b)


def test_capture_with_non_square_images(tmp_path):
    out = gen.generate(tmp_path, scene="hole", views=2, size=(80, 56), seed=1, mesh_res=64)
    meta = json.loads((out / "transforms.json").read_text())
    assert (meta["w"], meta["h"], meta["cx"], meta["cy"]) == (80, 56, 40.0, 28.0)
    with Image.open(out / meta["frames"][1]["file_path"]) as img:
        assert img.size == (80, 56)
    _check_projection(out, range(2), n_samples=10_000)


def test_cli_writes_a_capture(tmp_path):
    gen.main(["--scene", "concave", "--views", "2", "--size", "48x40", "--mesh-res", "48",
              "--out", str(tmp_path / "cli")])
    meta = json.loads((tmp_path / "cli" / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (48, 40, 2)
    assert json.loads((tmp_path / "cli" / "scene_info.json").read_text())["scene"] == "concave"


# ---------------------------------------------------------------------------------------------
# the shipped sample
# ---------------------------------------------------------------------------------------------
def test_shipped_sample_is_complete_and_consistent():
    info = json.loads((SAMPLE / "scene_info.json").read_text())
    assert (info["scene"], info["views"], info["w"], info["h"], info["seed"]) == ("blocks", 40, 400, 400, 0)
    meta = json.loads((SAMPLE / "transforms.json").read_text())
    assert len(meta["frames"]) == 40
    assert all((SAMPLE / f["file_path"]).is_file() for f in meta["frames"])
    total = sum(p.stat().st_size for p in SAMPLE.rglob("*") if p.is_file())
    assert total < 6e6, f"the shipped sample grew to {total / 1e6:.1f} MB"
    _check_projection(SAMPLE, [0, 17, 39], n_samples=100_000)


@pytest.mark.slow
def test_shipped_sample_registers_fully_with_sift_sfm(tmp_path):
    """~25 s: the texture must give SIFT enough to register every view (pycolmap, as the poses
    stage runs it: one SIMPLE_RADIAL camera, max_image_size 400, exhaustive matching)."""
    pycolmap = pytest.importorskip("pycolmap")
    pycolmap.logging.minloglevel = 2
    pycolmap.set_random_seed(0)
    db = tmp_path / "database.db"
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = 400
    opts.num_threads = 2
    opts.use_gpu = False
    pycolmap.extract_features(db, SAMPLE / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=pycolmap.ImageReaderOptions(camera_model="SIMPLE_RADIAL"),
                              extraction_options=opts, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, matching_options=pycolmap.FeatureMatchingOptions(), device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(db, SAMPLE / "images", tmp_path / "sparse",
                                          options=pycolmap.IncrementalPipelineOptions())
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    assert best.num_reg_images() == 40
    assert best.compute_mean_reprojection_error() < 0.6
    # camera centres match the true ones up to a similarity (Umeyama), to 1% of the orbit radius
    meta = json.loads((SAMPLE / "transforms.json").read_text())
    truth = {Path(f["file_path"]).name: np.array(f["transform_matrix"])[:3, 3] for f in meta["frames"]}
    est = np.array([im.projection_center() for im in best.images.values()])
    ref = np.array([truth[im.name] for im in best.images.values()])
    a, b = est - est.mean(axis=0), ref - ref.mean(axis=0)
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / (a**2).sum()
    err = np.linalg.norm(scale * a @ rot.T - b, axis=-1)
    assert err.mean() < 0.01 * np.linalg.norm(b, axis=-1).mean()
