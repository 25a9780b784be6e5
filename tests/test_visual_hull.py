"""The visual hull the surface model starts from (issue 13): carving on exact silhouettes of a sphere, its signed
distance, the model saving and reloading it, and the start shape the train stage picks with its reason."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from recon.camera import look_at
from recon.capture.scene import Scene
from recon.errors import ReconError
from recon.evaluation.views import View
from recon.geometry.visual_hull import carve, free_space, hull_bounds, hull_silhouettes, visual_hull_sdf
from recon.nerf.surface import SurfaceConfig, SurfaceModel
from recon.plans.training import surface_start

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RADIUS = 0.5
RES = 41  # cell 0.05
SIZE, FOCAL = 96, 110.0  # the sphere spans ~28 pixels from 4 units: a pixel is ~0.036 units there


def _silhouette(c2w: np.ndarray, size: int = SIZE, focal: float = FOCAL) -> np.ndarray:
    """(size, size) bool: the pixels whose centre ray hits the sphere of RADIUS at the origin."""
    v, u = np.mgrid[0:size, 0:size] + 0.5
    d = np.stack([(u - size / 2) / focal, -(v - size / 2) / focal, -np.ones_like(u)], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    closest = o - (o @ d.reshape(-1, 3).T).reshape(size, size)[..., None] * d  # nearest point of each ray to 0
    return np.linalg.norm(closest, axis=-1) < RADIUS


def _ring_cameras(elevations: tuple[float, ...] = (-40.0, 0.0, 40.0), n: int = 12) -> list[np.ndarray]:
    out = []
    for el in np.radians(elevations):
        for az in np.linspace(0, 2 * np.pi, n, endpoint=False):
            eye = 4.0 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            out.append(look_at(eye, np.zeros(3)))
    return out


def _grid_points() -> np.ndarray:
    axes = [np.linspace(BOX[0, i], BOX[1, i], RES) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


INTR = (FOCAL, FOCAL, SIZE / 2, SIZE / 2)


def test_the_hull_of_exact_silhouettes_keeps_the_sphere_and_carves_what_the_rims_show() -> None:
    cams = _ring_cameras()
    inside, carved_by = carve(BOX, RES, cams, [INTR] * len(cams), [_silhouette(c) for c in cams])
    true_sdf = np.linalg.norm(_grid_points(), axis=-1) - RADIUS
    pixel = 4.0 * 1.0 / FOCAL  # a pixel's footprint at the cameras' distance, ~0.036
    assert inside[true_sdf < -pixel].all()  # nothing of the object is carved (a pixel's rounding aside)
    assert not inside[true_sdf > 0.08].any()  # 36 views from three rings leave no lump more than 0.08 out
    assert inside.sum() < 1.3 * (true_sdf < 0).sum()
    assert carved_by[0, 0, 0] >= 2 and carved_by[RES // 2, RES // 2, RES // 2] == 0


def test_a_photo_carves_only_what_lies_in_its_frame_and_min_views_counts_photos() -> None:
    cam = look_at(np.array([4.0, 0.0, 0.0]), np.zeros(3))
    intr = (200.0, 200.0, SIZE / 2, SIZE / 2)  # the frame spans |y|, |z| < 0.96 at x = 0, 0.64 at x = 1
    sil = [_silhouette(cam, focal=200.0)]
    inside, carved_by = carve(BOX, RES, [cam], [intr], sil)
    c = RES // 2
    assert carved_by[c, 35, c] == 1 and not inside[c, 35, c]  # (0, 0.75, 0): in the frame, beside the sphere
    assert carved_by[-1, -1, -1] == 0 and inside[-1, -1, -1]  # (1, 1, 1): outside the frame, nothing known
    assert inside[c, c, c]
    inside2, _ = carve(BOX, RES, [cam], [intr], sil, min_views=2)
    assert inside2.all()  # one photo cannot carve what two must agree on
    wide, _ = carve(BOX, RES, [cam], [intr], sil, margin_px=6)
    assert not inside[~wide].any() and wide.sum() > inside.sum()  # a margin only keeps more


def test_the_hull_bounds_hold_the_sphere_ignore_one_wrong_mask_and_what_few_photos_see() -> None:
    cams = _ring_cameras()
    sils = [_silhouette(c) for c in cams]
    bounds = hull_bounds(BOX, RES, cams, [INTR] * len(cams), sils)
    cell = 0.05
    assert bounds is not None
    assert (bounds[0] <= -RADIUS + cell).all() and (bounds[1] >= RADIUS - cell).all()  # the sphere, to a cell
    assert (bounds[0] >= -RADIUS - 0.1).all() and (bounds[1] <= RADIUS + 0.1).all()  # the hull's lumps at most
    for everything in (True, False):  # one photo calls everything object, or nothing: the others decide
        wrong = [s.copy() for s in sils]
        wrong[0][:] = everything
        assert np.allclose(hull_bounds(BOX, RES, cams, [INTR] * len(cams), wrong), bounds)
    # a ring of narrow photos at the equator that call everything object: the grid's top and bottom lie beyond their
    # frames, so what counts is what enough of them see
    equator = _ring_cameras((0.0,))
    narrow = [(300.0, 300.0, SIZE / 2, SIZE / 2)] * len(equator)
    full = [np.ones((SIZE, SIZE), bool)] * len(equator)
    any_photo = hull_bounds(BOX, RES, equator, narrow, full, min_seen=0.0)
    most = hull_bounds(BOX, RES, equator, narrow, full, min_seen=0.9)
    assert any_photo[1, 2] < 0.9 and any_photo[0, 2] > -0.9  # what no photo sees is not object
    assert (most[1] - most[0] < any_photo[1] - any_photo[0]).all()
    assert hull_bounds(BOX, RES, equator, narrow, [np.zeros((SIZE, SIZE), bool)] * len(equator)) is None
    # what lies behind the plane the object stands on is not object, however many photos see the object there
    floor = hull_bounds(BOX, RES, equator, narrow, full, min_seen=0.0, support=np.array([0.0, 0.0, 1.0, -0.2]))
    assert floor[0, 2] == pytest.approx(-0.25) and np.allclose(floor[1], any_photo[1])  # a cell below the plane


def test_the_hull_sdf_is_a_signed_distance_zero_on_the_sphere_and_closed_in_its_box() -> None:
    cams = _ring_cameras()
    inside, _ = carve(BOX, RES, cams, [INTR] * len(cams), [_silhouette(c) for c in cams])
    sdf = visual_hull_sdf(inside, BOX)
    true_sdf = np.linalg.norm(_grid_points(), axis=-1) - RADIUS
    band = np.abs(true_sdf) < 0.3
    assert np.abs(sdf - true_sdf)[band].max() < 0.09  # the hull's lumps (< 0.08) and half a cell
    assert np.abs(sdf - true_sdf)[band].mean() < 0.03
    assert sdf[RES // 2, RES // 2, RES // 2] < -0.35  # deep inside (the smoothing rounds the distance's peak)
    assert (sdf[[0, -1]] > 0).all() and (sdf[:, [0, -1]] > 0).all() and (sdf[:, :, [0, -1]] > 0).all()
    full = np.ones((RES,) * 3, bool)  # nothing carved: the box itself, closed inside its faces
    box_sdf = visual_hull_sdf(full, BOX, smooth_cells=0)
    assert box_sdf[RES // 2, RES // 2, RES // 2] == pytest.approx(-(1.0 - 0.025), abs=1e-6)  # faces half a cell in
    with pytest.raises(ValueError, match="nothing is left"):
        visual_hull_sdf(np.zeros((RES,) * 3, bool), BOX)


def _cfg(**kw) -> SurfaceConfig:
    return SurfaceConfig(aabb=tuple(map(tuple, BOX)), sdf_res=RES, sdf_levels=2, feature_res=8, feature_dim=4, **kw)


def test_the_model_starts_from_the_hull_it_is_given_and_saves_it_with_its_weights() -> None:
    true_sdf = (np.linalg.norm(_grid_points(), axis=-1) - RADIUS).astype(np.float32)
    model = SurfaceModel(_cfg(init_shape="visual_hull"))
    x = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, -0.8]])
    assert torch.isnan(model.sdf(x)).all()  # no start shape yet: it cannot train unnoticed from an unset one
    model.set_initial_sdf(true_sdf)
    np.testing.assert_allclose(model.sdf(x).detach().numpy(), [-0.5, 0.0, 0.3], atol=0.02)
    reloaded = SurfaceModel(_cfg(init_shape="visual_hull"))
    reloaded.load_state_dict(model.state_dict())
    assert torch.equal(reloaded.sdf(x), model.sdf(x))
    with pytest.raises(ValueError, match="finite"):
        model.set_initial_sdf(true_sdf[:-1])
    with pytest.raises(ValueError, match="visual_hull"):
        SurfaceModel(_cfg()).set_initial_sdf(true_sdf)
    assert "prior_volume" not in SurfaceModel(_cfg()).state_dict()  # the hull's planes are rebuilt from the config


def _views(alpha: bool) -> list[View]:
    cams = _ring_cameras()
    out = []
    for k, c2w in enumerate(cams):
        sil = _silhouette(c2w)
        rgb = np.where(sil[..., None], 90, 255).astype(np.uint8) * np.ones(3, np.uint8)
        image = np.concatenate([rgb, (sil * 255).astype(np.uint8)[..., None]], -1) if alpha else rgb
        out.append(View(f"v{k}", image, c2w, INTR, 0.0, 0.0))
    return out


def _scene_points() -> np.ndarray:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    return RADIUS * d / np.linalg.norm(d, axis=-1, keepdims=True)


@pytest.mark.parametrize("shape, alpha, expect", [
    ("auto", True, "visual_hull"), ("auto", False, "hull"), ("visual_hull", True, "visual_hull"),
    ("hull", True, "hull"), ("sphere", True, "sphere"), ("visual_hull", False, "error"),
])
def test_the_start_shape_is_the_visual_hull_when_the_photos_have_silhouettes(shape: str, alpha: bool, expect: str) -> None:
    from dataclasses import asdict

    scene = Scene(frames=[], aabb=tuple(map(tuple, BOX)), capture="object", points=_scene_points())
    kwargs = {"config": asdict(_cfg(init_shape=shape))}
    if expect == "error":
        with pytest.raises(ReconError, match="silhouettes"):
            surface_start(kwargs, scene, _views(alpha))
        return
    settled, volume, why = surface_start(kwargs, scene, _views(alpha))
    assert settled["config"]["init_shape"] == expect
    assert (volume is not None) == (expect == "visual_hull")
    assert bool(settled["config"]["init_planes"]) == (expect == "hull")
    assert why.startswith("initial surface: ") and {"visual_hull": "visual hull", "hull": "convex hull",
                                                     "sphere": "a sphere"}[expect] in why
    model = SurfaceModel(SurfaceConfig(**{**settled["config"], "aabb": tuple(map(tuple, BOX))}))
    if volume is not None:
        model.set_initial_sdf(volume)
    f = model.sdf(torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9]])).detach()
    assert f[0] < -0.3 and f[1] > 0.3  # each start is closed around the sphere's middle


def test_the_start_shape_says_why_it_is_not_the_visual_hull() -> None:
    from dataclasses import asdict

    scene = Scene(frames=[], aabb=tuple(map(tuple, BOX)), capture="object", points=_scene_points())
    blank = [View(v.name, np.concatenate([v.image[..., :3], np.zeros_like(v.image[..., :1])], -1), v.c2w, v.intrinsics,
                  0.0, 0.0) for v in _views(True)]  # masks that call every pixel background
    settled, volume, why = surface_start({"config": asdict(_cfg())}, scene, blank)
    assert volume is None and settled["config"]["init_shape"] == "hull" and "leave nothing of the box" in why
    with pytest.raises(ReconError, match="Check the masks"):
        surface_start({"config": asdict(_cfg(init_shape="visual_hull"))}, scene, blank)
    _, _, why = surface_start({"config": asdict(_cfg(init_shape="hull"))}, scene, _views(True))
    assert "(train.surface.init_shape=hull)" not in why and "train.surface.init_shape=hull" in why
    _, _, why = surface_start({"config": asdict(_cfg())}, scene, _views(False))
    assert "the photos have no silhouettes" in why
    few = Scene(frames=[], aabb=tuple(map(tuple, BOX)), capture="object", points=_scene_points()[:5])
    settled, _, why = surface_start({"config": asdict(_cfg())}, few, _views(False))
    assert settled["config"]["init_shape"] == "sphere" and "only 5 sparse points" in why


@pytest.fixture(scope="module")
def surface_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, Path]:
    """The tiny sample scene's poses, trained 60 steps as the surface preset (small grids) and meshed."""
    import shutil

    import recon
    from tests.assets_scene import TINY, tiny_scene

    photos, scene_dir, _, _ = tiny_scene(tmp_path_factory)
    out = tmp_path_factory.mktemp("surface") / "scene"
    out.mkdir()
    for name in ("01_poses", "02_scene"):
        shutil.copytree(scene_dir / name, out / name)
    manifest = json.loads((scene_dir / "manifest.json").read_text())
    manifest["stages"] = {k: v for k, v in manifest["stages"].items() if k in ("poses", "normalize")}
    (out / "manifest.json").write_text(json.dumps(manifest))
    small = {"train.surface.sdf_res": 32, "train.surface.sdf_levels": 2, "train.surface.feature_res": 16}
    return recon.run(photos, out=out, preset="surface", overrides={**TINY, **small}), out


def test_the_surface_preset_starts_from_the_keyed_photos_visual_hull_and_keeps_it_in_the_field(surface_run) -> None:
    from recon.field import load_field

    result, out = surface_run
    metrics = json.loads((out / "03_field" / "metrics.json").read_text())
    assert [(s.name, s.action) for s in result.stages.values()] == [
        ("poses", "cached"), ("normalize", "cached"), ("train", "ran"), ("mesh", "ran")]
    assert any(r.startswith("initial surface: the visual hull of the 35 training photos' silhouettes") for r in metrics["reasons"])
    model, _ = load_field(out / "03_field")
    assert model.config.init_shape == "visual_hull" and torch.isfinite(model.prior_volume).all()
    assert float(model.prior_volume.min()) < 0 < float(model.prior_volume.max())
    assert result.mesh["watertight"] is True  # the zero set of a closed start, 60 steps on


def test_hull_silhouettes_cover_each_photos_object_and_outvote_one_wrong_mask() -> None:
    """Each photo's silhouette of the common hull covers its object pixels (the hull holds the sphere) and not much
    more; one photo's mask missing half the sphere carves nothing the others show while the tolerance allows one
    dissenting photo, and carves it from every photo when it allows none."""
    cams = _ring_cameras()
    masks = [_silhouette(c) for c in cams]
    wrong = [m.copy() for m in masks]
    wrong[5][:, : SIZE // 2] = False
    sil, carved_by = hull_silhouettes(BOX, RES, cams, [INTR] * len(cams), wrong, tolerance=1 / len(cams))
    assert carved_by.shape == (RES,) * 3 and len(sil) == len(cams)
    for i, (s, m) in enumerate(zip(sil, masks, strict=True)):
        assert s.shape == m.shape and (s & m).sum() >= 0.99 * m.sum(), i  # the sphere, whole, in every photo
        assert s.sum() <= 1.3 * m.sum(), i  # and the hull's splats only a few pixels beyond its outline
    wrong[6][:, : SIZE // 2] = False  # a second photo beside it cuts the same side: more than the tolerance
    outvoted, _ = hull_silhouettes(BOX, RES, cams, [INTR] * len(cams), wrong, tolerance=1 / len(cams))
    assert (outvoted[5] & masks[5]).sum() < 0.9 * masks[5].sum()
    voters = [i not in (5, 6) for i in range(len(cams))]  # the two photos carve nothing, and get their silhouettes
    unvoted, _ = hull_silhouettes(BOX, RES, cams, [INTR] * len(cams), wrong, tolerance=1 / len(cams), voters=voters)
    assert len(unvoted) == len(cams)
    assert (unvoted[5] & masks[5]).sum() >= 0.99 * masks[5].sum()


def test_a_close_ups_hull_silhouette_has_no_holes_on_the_near_side() -> None:
    """A camera 0.3 units from the sphere sees its near side's grid vertices three to four times as far apart as its
    rim's: each vertex is splatted as wide as a cell at its own depth, so the near side leaves no holes, and the
    silhouette still ends within a cell of the sphere's outline."""
    from scipy.ndimage import binary_erosion

    from recon.geometry.visual_hull import silhouette

    points = _grid_points()
    inside = np.linalg.norm(points, axis=-1) <= RADIUS
    shell = inside & ~binary_erosion(inside)
    eye = 0.8 * np.array([np.cos(0.3), np.sin(0.3), 0.4])
    c2w = look_at(eye, np.array([0.0, 0.1, -0.1]))
    cell = float(BOX[1, 0] - BOX[0, 0]) / (RES - 1)
    size, focal = 160, 120.0
    sil = silhouette(points[shell], cell, c2w, np.array([focal, focal, size / 2, size / 2]), size, size)
    truth = _silhouette(c2w, size=size, focal=focal)
    assert 0.2 < truth.mean() < 0.95  # the sphere crops the frame on one side and leaves room on the other
    assert (sil & truth).sum() >= 0.995 * truth.sum()  # one spacing for all missed 1.4% of it
    assert (sil & ~truth).sum() <= 0.15 * truth.sum()


def test_sightlines_to_a_bowls_inner_surface_free_its_hollow_that_the_silhouettes_fill() -> None:
    """A bowl (the lower half of the sphere's shell, open upwards) seen from a ring above: its silhouettes carve
    the half-ball whole, hollow included. The sightlines from the cameras to points on its inner surface free the
    hollow down to a cell and a half above the surface; the shell under it, and everything outside the bowl that no
    sightline passes, stay; one false point's sightlines free nothing where they do not cross."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    inner = 0.7 * RADIUS * d * np.where(d[:, 2:] < 0, 1.0, -1.0)  # the lower hemisphere, inside: a 3-cell wall
    eyes = [c2w[:3, 3] for c2w in _ring_cameras(elevations=(50.0, 70.0), n=8)]
    lines = []
    for eye in eyes:  # a point is seen when its sightline enters the bowl through the opening at the rim
        t = eye[2] / (eye[2] - inner[:, 2])
        rim = eye[:2] + t[:, None] * (inner[:, :2] - eye[:2])
        lines.append((eye, inner[np.linalg.norm(rim, axis=1) < 0.7 * RADIUS]))
    free = free_space(BOX, RES, lines)
    axis = np.linspace(-1.0, 1.0, RES)
    centre = RES // 2

    def at(z: float) -> bool:
        return bool(free[centre, centre, int(np.argmin(np.abs(axis - z)))])

    assert at(0.0) and at(-0.2)  # the hollow, below the rim and down to 3 cells (of 0.05) above its surface
    assert not at(-0.45) and not at(-0.6)  # the wall (0.35-0.5 down) and what lies under it
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1)
    wall = (np.linalg.norm(grid, axis=-1) >= 0.4) & (np.linalg.norm(grid, axis=-1) <= RADIUS) & (grid[..., 2] < -0.1)
    assert not free[wall].any()  # its wall, a cell in from the surface the points lie on, keeps every vertex
    one = free_space(BOX, RES, [(eyes[0], np.array([[0.3, 0.3, -0.3]])), (eyes[4], np.array([[0.3, 0.3, -0.3]]))])
    assert one.sum() <= 4  # two sightlines to one point meet only near it, where they stop short
    assert free_space(BOX, RES, lines, min_votes=1).sum() >= free.sum()


def test_the_sightlines_are_each_training_photos_camera_and_the_points_it_observes() -> None:
    """`sightlines_of`: a photo the scene records no observations for (an import) has none."""
    from recon.capture.scene import Frame
    from recon.plans.training import sightlines_of

    cams = _ring_cameras(elevations=(30.0,), n=3)
    frames = [Frame(f"v{k}.png", c2w, FOCAL, FOCAL, SIZE / 2, SIZE / 2, SIZE, SIZE) for k, c2w in enumerate(cams)]
    points = _scene_points()
    scene = Scene(frames=frames, points=points, point_visibility={"v0.png": np.arange(10), "v2.png": np.arange(5, 8)})
    lines = sightlines_of(scene, frames)
    assert len(lines) == 2
    assert np.allclose(lines[0][0], cams[0][:3, 3]) and np.allclose(lines[0][1], points[:10])
    assert np.allclose(lines[1][0], cams[2][:3, 3]) and np.allclose(lines[1][1], points[5:8])
