"""The mesh stage on an analytic radiance field (a soft sphere with a direction-dependent color):
resolution choice, the extracted radius, colors baked from rendered photos, exports, previews, and
`compare_to_gt` in the known-pose and SfM cases — all against closed forms, no training."""
from __future__ import annotations

import dataclasses
import json
import math
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from torch import Tensor

from recon.app.progress import Reporter
from recon.camera import look_at, pixel_footprint
from recon.capture.normalization import similarity, transform_c2w
from recon.capture.scene import Frame, Scene, spread_evenly
from recon.config import MeshConfig
from recon.evaluation.mesh_eval import compare_to_gt, format_comparison
from recon.evaluation.views import View, render_view
from recon.geometry.clean import clean_mesh
from recon.geometry.compare import chamfer_fscore
from recon.geometry.export import Z_UP_TO_Y_UP, export_transform
from recon.geometry.extract import choose_resolution, density_grid, grid_spacing, marching_cubes
from recon.geometry.preview import render_preview
from recon.geometry.raster import mesh_depth
from recon.meshing import extraction as field_mesh
from recon.meshing import photos as mesh_views
from recon.plans import mesh as mesh_plan
from recon.stages import mesh as mesh_stage
from tests.analytic_sphere import AABB, BACKGROUND, CENTRE, R0, SoftSphere, ring_views, sphere_color
from tests.analytic_sphere import run_mesh_stage as _run_stage
from tests.analytic_sphere import write_scene_dir as _scene_dir


# ---------------------------------------------------------------------------------------- resolution
def test_pixel_footprint_and_training_focal_closed_form() -> None:
    centres = np.array([[4.0, 0, 0], [0, 4.0, 0], [0, 0, -4.0]])
    fp, dist = pixel_footprint(AABB, centres, np.array([400.0, 400.0, 400.0]))
    assert dist == pytest.approx(4.0) and fp == pytest.approx(0.01)
    frame = Frame("a.jpg", np.eye(4), 1000.0, 1000.0, 400.0, 300.0, 800, 600)
    assert mesh_plan.training_focal(frame, 400) == pytest.approx(500.0)  # photo halved to 400 px
    assert mesh_plan.training_focal(frame, 2000) == pytest.approx(1000.0)  # never upscaled


def test_resolution_follows_footprint_and_is_capped_by_max_and_memory() -> None:
    shape, why = choose_resolution(AABB, MeshConfig(max_resolution=384), 0.01)
    assert shape == (201, 201, 201) and "footprint" in why  # 2 units / 0.01 = 200 cells
    shape, why = choose_resolution(AABB, MeshConfig(max_resolution=128), 0.01)
    assert shape == (128, 128, 128) and "max_resolution" in why
    shape, why = choose_resolution(AABB, MeshConfig(max_resolution=384, memory_budget_mb=1), 0.01)
    assert 4 * math.prod(shape) <= 2**20 and shape[0] >= 60 and "memory_budget_mb" in why  # 64³ floats = 1 MiB
    flat = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])
    shape, _ = choose_resolution(flat, MeshConfig(resolution=101), None)
    assert shape == (101, 101, 51)  # cubic cells: half the nodes on the half-height axis
    shape, why = choose_resolution(AABB, MeshConfig(resolution=512, memory_budget_mb=8), None)
    assert 4 * math.prod(shape) <= 8 * 2**20 and "lowered from 512" in why


# ---------------------------------------------------------------------------------------- extraction
@pytest.mark.parametrize(("coarse_to_fine", "nodes", "mode"), [(False, 65, "dense"), (True, 65, "dense"), (True, 161, "coarse-to-fine")])
def test_extracted_surface_is_the_analytic_iso_sphere(coarse_to_fine: bool, nodes: int, mode: str) -> None:
    cell = 2.0 / (nodes - 1)
    iso = -math.log(1 - field_mesh.ISO_OPACITY) / cell  # one cell of this σ is ISO_OPACITY opaque
    model = SoftSphere(amplitude=2 * iso, width=0.05)  # the auto iso sits at the profile's inflection
    shape = (nodes,) * 3
    cfg = MeshConfig(coarse_to_fine=coarse_to_fine)
    v, f, info = field_mesh.extract_mesh(model, torch.tensor(AABB, dtype=torch.float32), shape, cfg, Reporter(quiet=True))
    assert info["mode"] == mode  # 65 nodes: a 64-node coarse grid would refine nothing
    assert info["iso"] == pytest.approx(iso, rel=1e-6)
    r_iso = model.radius_at(info["iso"])
    r = np.linalg.norm(v - CENTRE, axis=1)
    assert abs(r.mean() - r_iso) < 0.02 * cell and np.abs(r - r_iso).max() < 0.1 * cell
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r_iso).apply_translation(CENTRE)
    cmp = chamfer_fscore((v, f), sphere, n_samples=50_000)
    floor = chamfer_fscore(trimesh.creation.icosphere(4, r_iso).apply_translation(CENTRE), sphere, n_samples=50_000)
    assert cmp["chamfer_l1"] < 1.05 * floor["chamfer_l1"]  # as close as a perfect sphere, at this sampling
    assert cmp["fscore@0.01"] > 0.99
    if mode == "coarse-to-fine":
        assert info["evaluated"] < 0.5 * math.prod(shape)


def test_explicit_iso_is_used_as_given() -> None:
    model = SoftSphere(amplitude=400.0, width=0.05)
    v, _, info = field_mesh.extract_mesh(
        model, torch.tensor(AABB, dtype=torch.float32), (49, 49, 49), MeshConfig(iso=200.0), Reporter(quiet=True)
    )
    assert info["iso"] == 200.0 and "set by caller" in info["iso_reason"]
    assert np.linalg.norm(v - CENTRE, axis=1).mean() == pytest.approx(R0, abs=2e-3)  # σ = A/2 at r = R0


class HollowSphere(SoftSphere):
    """The soft sphere with an empty inside (r < 0.4) reached through a pit 2 cells wide at the top: the shell
    a radiance field trains, which marching cubes meshes twice (outer surface and inner wall)."""

    def density(self, x: Tensor) -> Tensor:
        d = x - torch.as_tensor(CENTRE, dtype=x.dtype, device=x.device)
        r = d.norm(dim=-1)
        pit = (d[:, :2].norm(dim=-1) < 0.03) & (d[:, 2] > 0)
        return torch.where((r < 0.4) | pit, torch.zeros_like(r), super().density(x))


def test_fill_cavities_removes_the_inner_wall_of_a_hollow_field() -> None:
    model = HollowSphere(amplitude=400.0, width=0.02)
    aabb = torch.tensor(AABB, dtype=torch.float32)
    walls = {}
    for k in (0, 3):
        v, _, info = field_mesh.extract_mesh(model, aabb, (81, 81, 81), MeshConfig(iso=200.0, fill_cavities=k),
                                             Reporter(quiet=True))
        walls[k] = float((np.linalg.norm(v - CENTRE, axis=1) < 0.5).mean())
        assert ("fill" in info) == (k > 0)
    assert walls[0] > 0.2  # the inner wall is meshed
    assert walls[3] < 0.02  # filled: only the pit's short throat stays below r = 0.5
    assert info["fill"]["filled_nodes"] > 0.8 * (4 / 3 * math.pi * 0.4**3) / (2.0 / 80) ** 3


def test_a_field_without_surface_fails_with_advice() -> None:
    model = SoftSphere(amplitude=400.0, width=0.05)
    model.density = lambda x: torch.full((x.shape[0],), 3.0)  # type: ignore[method-assign]
    with pytest.raises(Exception, match="No surface could be extracted"):
        field_mesh.extract_mesh(model, torch.tensor(AABB, dtype=torch.float32), (17, 17, 17), MeshConfig(), Reporter(quiet=True))


# ---------------------------------------------------------------------------------------- colors
def test_colors_baked_from_rendered_photos_match_the_analytic_color() -> None:
    model = SoftSphere(amplitude=3000.0, width=0.004, samples=384)
    views = ring_views(model)
    v, f, info = field_mesh.extract_mesh(
        model, torch.tensor(AABB, dtype=torch.float32), (97, 97, 97), MeshConfig(), Reporter(quiet=True)
    )
    normals = trimesh.Trimesh(v, f, process=False).vertex_normals
    depths = mesh_views.mesh_depths(v, f, views)
    colors, bake = mesh_views.bake_colors(model, views, depths, v, normals)
    err = np.abs(colors - sphere_color(v.astype(np.float64))).max(axis=1)
    assert bake["views"] == 8 and bake["seen"] > 0.9 * len(v)  # the depth test keeps the visible surface
    assert np.median(err) < 0.02 and np.percentile(err, 95) < 0.06
    # the photos, not the fallback, made the colors: a field with wrong colors bakes the same
    model.radiance = lambda x, d: torch.zeros(x.shape[0], 3)  # type: ignore[method-assign]
    colors_2, _ = mesh_views.bake_colors(model, views, depths, v, normals)
    seen = np.any(colors_2 > 0, axis=1)
    np.testing.assert_allclose(colors_2[seen], colors[seen], atol=1e-6)


def test_depth_is_rendered_small_and_upsampled_to_the_view() -> None:
    model = SoftSphere(amplitude=3000.0, width=0.004, samples=128)
    view = ring_views(model, n=1, size=40)[0]
    full = render_view(model, view, torch.tensor(AABB, dtype=torch.float32), BACKGROUND)["depth"]
    small = mesh_views.render_depth(model, view, torch.tensor(AABB, dtype=torch.float32), BACKGROUND, max_side=20)
    assert small.shape == full.shape
    assert np.median(np.abs(small - full)) < 0.02  # equal away from the silhouette


def test_spread_evenly_keeps_first_and_last() -> None:
    assert spread_evenly(list(range(100)), 5) == [0, 25, 50, 74, 99]
    assert spread_evenly([1, 2], 24) == [1, 2]


# ---------------------------------------------------------------------------------------- export / previews
def test_export_transform_source_frame_and_real_size() -> None:
    w2s = similarity(2.5, np.eye(3), np.array([1.0, 2.0, 3.0]))  # world_from_source
    s2w = np.linalg.inv(w2s)
    v = np.array([[0.0, 0, 0], [0.5, 0.2, 0.1]])
    t, _ = export_transform(v, "normalized", s2w, 0.0)
    assert t is None
    t, _ = export_transform(v, "source", s2w, 0.0)
    np.testing.assert_allclose(t, s2w)
    t, why = export_transform(v, "source", s2w, 2.0)
    mapped = v @ t[:3, :3].T + t[:3, 3]
    assert np.ptp(mapped, axis=0).max() == pytest.approx(2.0) and "scaled" in why


def test_preview_shows_the_colored_shaded_mesh_from_the_right_side() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    colors = np.where(sphere.vertices[:, 1:2] < 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])  # -Y half red
    front = render_preview(sphere.vertices, sphere.faces, colors, azimuth_deg=0, elevation_deg=0, size=64)
    back = render_preview(sphere.vertices, sphere.faces, colors, azimuth_deg=180, elevation_deg=0, size=64)
    assert front.shape == (64, 64, 3) and front.dtype == np.uint8
    assert (front[0, 0] == 255).all() and (front[32, 32, 0] > 2 * front[32, 32, 2])  # the camera on -Y sees red
    assert back[32, 32, 2] > 2 * back[32, 32, 0]
    lit, shadow = front[20, 22].astype(int), front[44, 42].astype(int)  # light from the upper left
    assert lit.sum() > shadow.sum()
    # the camera frames the sphere's silhouette (its projection) with a 5 % margin: a disc of 1/1.1 the width
    covered = (front != 255).any(axis=-1).mean()
    assert covered == pytest.approx(math.pi / 4 / 1.1**2, rel=0.08)
    inside = np.hypot(*np.mgrid[0:64, 0:64] + 0.5 - 32) < 0.9 * 32 / 1.1  # no gaps inside the silhouette
    assert (front[inside] != 255).any(axis=-1).all()


# ---------------------------------------------------------------------------------------- the stage, end to end
def test_stage_writes_reloadable_meshes_report_and_previews_and_gt_comparison_is_exact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = SoftSphere(amplitude=3000.0, width=0.004, samples=384)
    w2s = similarity(0.5, trimesh.transformations.rotation_matrix(0.7, [0.3, 0.2, 1.0])[:3, :3], np.array([0.2, -0.4, 1.0]))
    scene_dir = _scene_dir(tmp_path, model, w2s, kind="transforms")
    cfg = MeshConfig(resolution=97, target_faces=6000, frame="source", color="photos", texture_size=128)
    summary, out = _run_stage(scene_dir, model, cfg, monkeypatch)

    report = json.loads((out / "mesh_report.json").read_text())
    assert summary["watertight"] and summary["components_removed"] == 0 and "vertices" in summary["headline"]
    assert report["resolution"]["grid"] == [97, 97, 97] and report["peak_rss_mb"] > 0
    assert report["colors"]["views"] == 6 and report["colors"]["seen"] > 0.9 * report["vertices"]
    for name in ("mesh.glb", "mesh.obj", "mesh.ply", "preview_front.png", "preview_side.png"):
        assert (out / name).stat().st_size > 0
    # the ply is in the source frame, +Z up; the glb the same, rotated to +Y up
    s2w = np.linalg.inv(w2s)
    ply = trimesh.load(out / "mesh.ply", process=False)
    glb = trimesh.load(out / "mesh.glb", force="mesh", process=False)
    assert len(ply.vertices) == len(glb.vertices) == report["vertices"] and len(ply.faces) == report["faces"]
    centre_src = s2w[:3, :3] @ CENTRE + s2w[:3, 3]
    r_src = np.linalg.norm(ply.vertices - centre_src, axis=1) * 0.5  # world_from_source scale 0.5
    # a near-step σ profile puts marching cubes' vertices up to ~1/4 cell off the exact iso-surface
    assert r_src.mean() == pytest.approx(model.radius_at(report["iso"]), abs=0.25 * 2 / 96)
    np.testing.assert_allclose(glb.vertices, ply.vertices @ Z_UP_TO_Y_UP[:3, :3].T, atol=1e-5)
    world = ply.vertices @ w2s[:3, :3].T + w2s[:3, 3]
    rgb = np.asarray(ply.visual.vertex_colors)[:, :3] / 255.0
    assert np.median(np.abs(rgb - sphere_color(world)).max(axis=1)) < 0.03

    # compare_to_gt, known poses: GT = the analytic iso-sphere in the source frame → F ≈ 1
    gt = trimesh.creation.icosphere(subdivisions=5, radius=model.radius_at(report["iso"]) / 0.5)
    gt.apply_translation(centre_src)
    gt_path = tmp_path / "gt" / "gt_mesh.ply"
    gt_path.parent.mkdir()
    gt.export(gt_path)
    result = compare_to_gt(scene_dir, gt_path)
    assert result["alignment"]["method"].startswith("exact")
    assert result["fscore@0.01"] > 0.99 and result["chamfer_l1_rel"] < 3e-3
    assert result["volume_ratio"] == pytest.approx(1.0, abs=0.02)  # both closed: the solids compare too
    # the cameras, moved into the truth's frame, see the sphere they look at: the scores where they see it agree
    assert result["gt_seen_share"] > 0.95 and result["fscore_seen@0.01"] > 0.99
    assert "F-score" in format_comparison(result) and "of the true solid's" in format_comparison(result)

    # the same scene as if from SfM: the GT lives in another frame, the true poses say which
    true_from_source = similarity(3.0, trimesh.transformations.rotation_matrix(-1.1, [1.0, 0.0, 0.4])[:3, :3], np.array([5.0, 1.0, -2.0]))
    scene_json = scene_dir / "02_scene" / "scene.json"
    doc = json.loads(scene_json.read_text())
    doc["source_kind"] = "photos"
    scene_json.write_text(json.dumps(doc))
    gt.apply_transform(true_from_source)
    gt.export(gt_path)
    frames = [{"file_path": f"images/{Path(fr['file_path']).name}", "transform_matrix": transform_c2w(true_from_source @ s2w, np.asarray(fr["transform_matrix"])).tolist()} for fr in doc["frames"]]
    (gt_path.parent / "transforms.json").write_text(json.dumps({"fl_x": 128.0, "fl_y": 128.0, "cx": 32, "cy": 32, "w": 64, "h": 64, "frames": frames}))
    result = compare_to_gt(scene_dir, gt_path)
    assert result["alignment"]["cameras_matched"] == 6 and result["alignment"]["residual_rms_rel"] < 1e-9
    assert result["alignment"]["scale"] == pytest.approx(3.0)
    assert result["gt_seen_share"] > 0.95 and result["fscore_seen@0.01"] > 0.99  # the true cameras see it too
    assert result["fscore@0.01"] > 0.99 and result["chamfer_l1_rel"] < 3e-3
    # one true camera far from where SfM put it: the fit leaves it out (and names it) instead of moving the mesh
    frames[1]["transform_matrix"][0][3] += 2.0
    (gt_path.parent / "transforms.json").write_text(json.dumps({"fl_x": 128.0, "fl_y": 128.0, "cx": 32, "cy": 32, "w": 64, "h": 64, "frames": frames}))
    result = compare_to_gt(scene_dir, gt_path)
    assert result["alignment"]["cameras_fitted"] == 5 and result["alignment"]["residual_rms_rel"] < 1e-9
    assert list(result["alignment"]["cameras_left_out"]) == [Path(frames[1]["file_path"]).name]
    assert result["fscore@0.01"] > 0.99 and "left out of the fit" in format_comparison(result)
    (gt_path.parent / "transforms.json").unlink()
    with pytest.raises(Exception, match="no transforms.json"):
        compare_to_gt(scene_dir, gt_path)


def test_stage_field_colors_and_normalized_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = SoftSphere(amplitude=400.0, width=0.05, samples=64)
    scene_dir = _scene_dir(tmp_path, model, np.eye(4), kind="transforms")
    cfg = MeshConfig(resolution=33, target_faces=0, color="field", coarse_to_fine=False, real_size=3.0, texture_size=128)
    summary, out = _run_stage(scene_dir, model, cfg, monkeypatch)
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert np.ptp(ply.vertices, axis=0).max() == pytest.approx(3.0, rel=1e-5)
    report = json.loads((out / "mesh_report.json").read_text())
    assert report["colors"]["source"] == "field" and report["extraction"]["mode"] == "dense"
    scale = report["export"]["transform"][0][0]
    rgb = np.asarray(ply.visual.vertex_colors)[:, :3] / 255.0
    np.testing.assert_allclose(rgb, sphere_color(ply.vertices / scale), atol=3 / 255)


def test_hidden_walls_inside_a_soft_field_are_removed_and_the_visible_surface_kept() -> None:
    """A field that is a shell with a soft inside, plus an island of material in it: marching cubes finds the
    outer sphere, an inner wall and the island. Removing what the ring views do not see keeps only the outer
    sphere, whole."""
    model = SoftSphere(amplitude=3000.0, width=0.004, samples=384)
    views = ring_views(model)
    aabb_t = torch.tensor(AABB, dtype=torch.float32)
    depths = mesh_views.render_depths(model, views, aabb_t, BACKGROUND, None, Reporter(quiet=True))
    n = 65
    grid = density_grid(model.density, aabb_t, n)
    level = 0.5 * float(grid.max())
    lin = np.linspace(AABB[0][0], AABB[1][0], n)
    x, y, z = np.meshgrid(lin, lin, lin, indexing="ij")
    r = np.linalg.norm(np.stack([x, y, z], -1) - CENTRE, axis=-1)
    grid[r < 0.4] = 0.5 * level  # a soft inside below the level: an inner wall at r = 0.4
    grid[r < 0.15] = 2 * level  # an island in the middle, big enough to survive the floater rule
    vertices, faces = marching_cubes(grid, level, AABB)
    cell = float(grid_spacing(AABB, n).max())
    kept_all = clean_mesh(vertices, faces, AABB)[0]
    outer = np.linalg.norm(kept_all - CENTRE, axis=1) > 0.5
    assert (~outer).mean() > 0.2  # without the visibility test the inner wall and the island stay
    seen_fn = mesh_views.see_with_views(views, depths, 2 * cell)
    kept, _, report = clean_mesh(vertices, faces, AABB, seen_fn=seen_fn)
    radius = np.linalg.norm(kept - CENTRE, axis=1)
    assert np.abs(radius - model.radius_at(level)).max() < cell
    assert report["hidden"]["removed_faces"] > 0
    assert len(kept) >= 0.95 * outer.sum()  # the visible sphere is kept (nearly) whole


def test_hollow_fill_runs_for_objects_and_not_on_a_whole_unbounded_scene() -> None:
    from types import SimpleNamespace

    found, none = SimpleNamespace(region=[[0, 0, 0], [1, 1, 1]]), SimpleNamespace(region=None)
    cfg = MeshConfig(fill_cavities=4)
    assert mesh_plan.hollow_fill_applies(none, cfg, bounded=True)[0]  # an object capture: the box is the object's
    assert mesh_plan.hollow_fill_applies(found, cfg, bounded=False)[0]  # the object region of a scene
    assert mesh_plan.hollow_fill_applies(none, MeshConfig(fill_cavities=4, region="-1,-1,-1,1,1,1"), bounded=False)[0]
    applies, why = mesh_plan.hollow_fill_applies(none, cfg, bounded=False)
    assert not applies and "whole scene box" in why
    assert not mesh_plan.hollow_fill_applies(found, MeshConfig(fill_cavities=4, region="all"), bounded=False)[0]
    assert not mesh_plan.hollow_fill_applies(found, MeshConfig(fill_cavities=0), bounded=True)[0]


def test_a_closed_mesh_is_planned_for_an_object_keeps_every_face_and_caps_at_the_cut() -> None:
    region, ground = np.array([[-0.5] * 3, [0.5] * 3]), np.array([0.0, 0.0, 1.0, -0.5])
    scene = _capture(masks=True, region=region, ground=ground)
    plan = mesh_plan.plan_mesh(MeshConfig(resolution=65, closed=True), scene, PLAN_META, on_cpu=True, voxel=0.0)
    assert plan.closed and plan.hidden_tolerance is None and plan.uses_views  # its inside comes from the views
    assert "watertight solid" in plan.closed_why and "ground" in plan.closed_why and plan.closed_why in plan.notes
    # capped where open meshes are cut
    np.testing.assert_allclose(plan.support_plane, [0.0, 0.0, 1.0, -0.5 + plan.ground_margin])
    assert not mesh_plan.plan_mesh(MeshConfig(resolution=65), scene, PLAN_META, on_cpu=True, voxel=0.0).closed
    whole = _capture(masks=False)
    scattered = mesh_plan.plan_mesh(MeshConfig(resolution=65, closed=True), whole, {**PLAN_META, "bounded": False},
                                    on_cpu=True, voxel=0.0)
    assert not scattered.closed and "unbounded" in scattered.closed_why  # no object to close: said, not done


def test_unsure_masks_crop_the_mesh_of_a_field_trained_without_them_and_say_so() -> None:
    """The automatic masks normalize was not sure of crop the mesh of the field trained on the whole photos; not a
    masked capture's (its own masks do), not a closed solid, not with mesh.unsure_masks=off or without such masks."""
    plan = mesh_plan.plan_mesh(MeshConfig(resolution=65), _capture(masks=False), PLAN_META, on_cpu=True, voxel=0.0,
                               unsure_masks=True)
    assert plan.unsure_frames and len(plan.unsure_frames) <= mesh_plan.CPU_BAKE_VIEWS["fast"]
    assert "masks_unsure/" in plan.unsure_why and "mesh.unsure_masks=off" in plan.unsure_why
    assert plan.notes[-1] == plan.unsure_why and "at least 50% of" in plan.unsure_why
    for cfg, scene, unsure in ((MeshConfig(resolution=65), _capture(masks=False), False),
                               (MeshConfig(resolution=65, unsure_masks="off"), _capture(masks=False), True),
                               (MeshConfig(resolution=65), _capture(masks=True), True),
                               (MeshConfig(resolution=65, closed=True), _capture(masks=False), True)):
        other = mesh_plan.plan_mesh(cfg, scene, PLAN_META, on_cpu=True, voxel=0.0, unsure_masks=unsure)
        assert other.unsure_frames == [] and other.unsure_why == "" and other.unsure_why not in other.notes


def test_the_stage_crops_with_the_unsure_masks_it_finds_beside_the_scene(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Unsure masks in 02_scene/masks_unsure/ that call the whole sphere object keep every face; masks that call it
    background in every photo leave no surface (the stage says so), unless mesh.unsure_masks=off."""
    from recon.capture.images import save_image
    from recon.errors import ReconError

    model = SoftSphere(amplitude=400.0, width=0.05, samples=64)
    cfg = MeshConfig(resolution=33, target_faces=0, color="field", coarse_to_fine=False, texture_faces=0)
    faces = {}
    for label, white, setting in (("none", None, "auto"), ("all object", 1.0, "auto"),
                                  ("all background, off", 0.0, "off"), ("all background", 0.0, "auto")):
        scene_dir = _scene_dir(tmp_path / label.replace(" ", "_").replace(",", ""), model, np.eye(4), kind="transforms")
        if white is not None:
            folder = scene_dir / "02_scene" / "masks_unsure"
            folder.mkdir()
            for frame in json.loads((scene_dir / "02_scene" / "scene.json").read_text())["frames"]:
                save_image(folder / f"{Path(frame['file_path']).stem}.png", np.full((64, 64, 1), white, np.float32))
        run_cfg = dataclasses.replace(cfg, unsure_masks=setting)
        if label == "all background":
            with pytest.raises(ReconError, match="Every piece of the extracted surface was removed"):
                _run_stage(scene_dir, model, run_cfg, monkeypatch)
            continue
        summary, out = _run_stage(scene_dir, model, run_cfg, monkeypatch)
        report = json.loads((out / "mesh_report.json").read_text())
        faces[label] = summary["faces"]
        assert ("masked" in report["clean"]) == (label == "all object")
        assert (report["masks"] is not None and "unsure" in report["masks"]) == (label == "all object")
    assert faces["all object"] == faces["none"] == faces["all background, off"] > 0


def test_iso_opacity_is_lower_with_masks_unless_set() -> None:
    choose = mesh_plan.capture_iso_opacity
    assert choose(MeshConfig(), masked=False)[0] == 0.0  # 0: the stage's ISO_OPACITY
    opacity, why = choose(MeshConfig(), masked=True)
    assert opacity == mesh_plan.MASKED_ISO_OPACITY < field_mesh.ISO_OPACITY and "masks" in why
    assert choose(MeshConfig(iso_opacity=0.6), masked=True)[0] == 0.6
    assert choose(MeshConfig(iso=3.0), masked=True)[0] == 0.0  # an explicit level wins


# ---------------------------------------------------------------------------------------- the plan
PLAN_META = {"aabb": AABB.tolist(), "bounded": True, "max_side": 64, "kind": "fast"}


def _capture(masks: bool, **scene: object) -> Scene:
    """Six 64-px photos on a ring (the last held out), with masks or without: a scene to plan, no files needed."""
    frames = [Frame(f"v{i}.png", look_at(3.0 * np.array([math.cos(a), math.sin(a), 0.5]), np.zeros(3)),
                    128.0, 128.0, 32.0, 32.0, 64, 64, split="test" if i == 5 else "train",
                    mask_path=f"v{i}_mask.png" if masks else None)
              for i, a in enumerate(np.linspace(0, 2 * math.pi, 6, endpoint=False))]
    return Scene(frames=frames, aabb=AABB, **scene)  # type: ignore[arg-type]


def test_plan_lowers_the_iso_opacity_for_a_masked_capture_and_says_why() -> None:
    cfg = MeshConfig(resolution=65)
    plain = mesh_plan.plan_mesh(cfg, _capture(masks=False), PLAN_META, on_cpu=True, voxel=0.0)
    assert not plain.masked and plain.extraction.iso_opacity == field_mesh.ISO_OPACITY and plain.iso_why == ""
    masked = mesh_plan.plan_mesh(cfg, _capture(masks=True), PLAN_META, on_cpu=True, voxel=0.0)
    assert masked.masked and masked.extraction.iso_opacity == mesh_plan.MASKED_ISO_OPACITY
    assert "masks trained the background empty" in masked.iso_why
    # the reasons print in the stage's order: region, resolution, then the iso opacity
    assert masked.notes == [f"mesh region: {masked.region_why}", f"resolution: {masked.resolution_why}", masked.iso_why]
    assert masked.shape == (65, 65, 65) and "mesh.resolution=65" in masked.resolution_why
    chosen = mesh_plan.plan_mesh(MeshConfig(resolution=65, iso_opacity=0.5), _capture(masks=True), PLAN_META,
                                 on_cpu=True, voxel=0.0)
    assert chosen.extraction.iso_opacity == 0.5 and chosen.iso_why == ""  # the user's setting wins
    surface = mesh_plan.plan_mesh(cfg, _capture(masks=True), {**PLAN_META, "kind": "surface"}, on_cpu=True, voxel=0.0)
    assert surface.zero_set and surface.extraction is cfg and surface.hidden_tolerance is None  # no iso to choose


def test_plan_crops_to_the_object_region_cuts_the_ground_and_says_why() -> None:
    region, ground = np.array([[-0.5] * 3, [0.5] * 3]), np.array([0.0, 0.0, 1.0, -0.5])
    scene = _capture(masks=False, region=region, ground=ground)
    plan = mesh_plan.plan_mesh(MeshConfig(resolution=65), scene, PLAN_META, on_cpu=True, voxel=0.0)
    np.testing.assert_allclose(plan.region, [[-0.6] * 3, [0.6] * 3])  # the region +10% on each side
    assert "normalize's object region, +10%" in plan.region_why and "ground plane is cut away" in plan.region_why
    np.testing.assert_allclose(plan.ground, ground)
    assert plan.cell == pytest.approx(1.2 / 64) and plan.ground_margin == pytest.approx(2 * plan.cell)
    coarse = mesh_plan.plan_mesh(MeshConfig(resolution=65), scene, PLAN_META, on_cpu=True, voxel=0.05)
    assert coarse.cell == 0.05 and coarse.hidden_tolerance == pytest.approx(0.05)  # the field's voxel is coarser
    wide = mesh_plan.plan_mesh(MeshConfig(resolution=65, region_margin=0.5, keep_ground=True), scene, PLAN_META,
                               on_cpu=True, voxel=0.0)
    np.testing.assert_allclose(wide.region, AABB)  # +50%, clipped to the scene box
    assert wide.ground is None and "+50%" in wide.region_why and "ground plane is kept" in wide.region_why
    everything = mesh_plan.plan_mesh(MeshConfig(resolution=65, region="all"), scene, PLAN_META, on_cpu=True, voxel=0.0)
    assert everything.ground is None and everything.region_why == "the whole scene box (mesh.region=all)"


def test_plan_cuts_a_masked_capture_at_its_table_and_an_unmasked_one_a_layer_above_it() -> None:
    """Masks train the table empty, so the faces just above its plane are the object's base: cut at the plane. Without
    masks the field holds the table top as a layer about a voxel thick: cut it with the plane."""
    region, ground = np.array([[-0.5] * 3, [0.5] * 3]), np.array([0.0, 0.0, 1.0, -0.5])
    cfg = MeshConfig(resolution=65)
    plain = mesh_plan.plan_mesh(cfg, _capture(masks=False, region=region, ground=ground), PLAN_META, on_cpu=True,
                                voxel=0.0)
    assert plain.ground_margin == pytest.approx(mesh_plan.GROUND_LAYER_CELLS * plain.cell) and plain.ground_margin > 0
    assert plain.ground_margin_why == "" and plain.ground_layer == pytest.approx(plain.ground_margin)
    masked = mesh_plan.plan_mesh(cfg, _capture(masks=True, region=region, ground=ground), PLAN_META, on_cpu=True,
                                 voxel=0.0)
    assert masked.ground_margin == 0.0 and "table cut at its plane" in masked.ground_margin_why
    assert masked.ground_layer == pytest.approx(plain.ground_layer)  # the coherence check still leaves the table out
    assert masked.notes == [f"mesh region: {masked.region_why}", f"resolution: {masked.resolution_why}",
                            masked.ground_margin_why, masked.iso_why]
    wall = mesh_plan.plan_mesh(cfg, _capture(masks=True, region=region, ground=np.array([1.0, 0.0, 0.0, -0.5])),
                               PLAN_META, on_cpu=True, voxel=0.0)
    assert wall.ground_margin == 0.0 and "wall cut at its plane" in wall.ground_margin_why
    chosen = mesh_plan.plan_mesh(MeshConfig(resolution=65, ground_margin_cells=1.0),
                                 _capture(masks=True, region=region, ground=ground), PLAN_META, on_cpu=True, voxel=0.0)
    assert chosen.ground_margin == pytest.approx(chosen.cell) and chosen.ground_margin_why == ""  # the user's wins
    kept = mesh_plan.plan_mesh(MeshConfig(resolution=65, keep_ground=True),
                               _capture(masks=True, region=region, ground=ground), PLAN_META, on_cpu=True, voxel=0.0)
    assert kept.ground is None and kept.ground_margin_why == ""  # nothing is cut, nothing to say


def test_plan_picks_the_photos_to_check_and_color_against() -> None:
    scene = _capture(masks=False)
    cpu = mesh_plan.plan_mesh(MeshConfig(resolution=65), scene, PLAN_META, on_cpu=True, voxel=0.0)
    assert len(cpu.view_frames) == 5 and cpu.depth_side == 200 and cpu.views_why == "5 of 5 training views, depth rendered at ≤ 200 px"
    assert [f.name for f in cpu.held_out_frames] == ["v5.png"] and cpu.held_out_why == "1 of 1"
    few = mesh_plan.plan_mesh(MeshConfig(resolution=65, cpu_bake_views=2, cpu_depth_side=32), scene,
                              {**PLAN_META, "kind": "classic"}, on_cpu=True, voxel=0.0)
    assert [f.name for f in few.view_frames] == ["v0.png", "v4.png"] and few.depth_side == 32
    assert "2 of 5 training views (spread evenly; at most 2 on the CPU for the classic model" in few.views_why
    gpu = mesh_plan.plan_mesh(MeshConfig(resolution=65), scene, PLAN_META, on_cpu=False, voxel=0.0)
    assert len(gpu.view_frames) == 5 and gpu.depth_side is None  # fewer photos than GPU_BAKE_VIEWS: all of them
    gpu_few = mesh_plan.plan_mesh(MeshConfig(resolution=65, gpu_bake_views=3), scene, PLAN_META, on_cpu=False, voxel=0.0)
    assert [f.name for f in gpu_few.view_frames] == ["v0.png", "v2.png", "v4.png"] and gpu_few.depth_side is None
    assert "at most 3 on a GPU" in gpu_few.views_why
    field = mesh_plan.plan_mesh(MeshConfig(resolution=65, color="field", drop_hidden=False, texture_faces=0), scene,
                                PLAN_META, on_cpu=True, voxel=0.0)
    assert not field.uses_views and field.view_frames == [] and not field.texture and field.held_out_frames == []


def test_bake_depths_are_the_mesh_z_buffer_without_its_silhouette_rim() -> None:
    # a square x, y in [-1, 1] at z = -4 facing a camera at the origin (f = 50, 64 px): pixel centres i + 0.5 within
    # 32 ± 12.5 (edges included), i.e. pixels 19..44
    square = np.array([[-1.0, -1.0, -4.0], [1.0, -1.0, -4.0], [1.0, 1.0, -4.0], [-1.0, 1.0, -4.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    view = View("v", np.zeros((64, 64, 3), np.uint8), np.eye(4), (50.0, 50.0, 32.0, 32.0), 0.1, 10.0)
    (z,) = mesh_views.mesh_depths(square, faces, [view])
    covered = np.zeros((64, 64), bool)
    covered[19:45, 19:45] = True
    inner = np.zeros_like(covered)
    inner[20:44, 20:44] = True  # the rim next to empty pixels is left out
    full = mesh_depth(square, faces, np.eye(4), view.intrinsics, (64, 64))
    assert np.allclose(full[covered], 4.0) and np.all(np.isinf(full[~covered]))
    assert np.all(np.isinf(z[~inner])) and np.allclose(z[inner], 4.0)
    # a vertex in the middle is seen at its depth; one behind the square (a hidden one) is not
    _, info = mesh_views.bake_colors(SoftSphere(400.0, 0.05), [view], [z], np.array([[0.0, 0.0, -4.0], [0.0, 0.0, -6.0]]),
                                     np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), depth_tol=0.05)
    assert info["seen"] == 1 and info["unseen_from_field"] == 1


def test_the_textured_copy_is_unwrapped_beside_the_stages_next_steps(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """xatlas takes seconds on a full-size mesh: the stage starts the unwrap right after cleaning, in a thread, and
    checks, colours and exports the mesh meanwhile. Here the unwrap waits (at most 30 s) for the coherence check to
    start: run one after the other, it would see it never start."""
    model = SoftSphere(amplitude=400.0, width=0.05, samples=64)
    scene_dir = _scene_dir(tmp_path, model, np.eye(4), kind="transforms")
    coherence_started, seen = threading.Event(), {}
    real_unwrap, real_coherence = mesh_stage.unwrap_mesh, mesh_stage.coherence

    def waiting_unwrap(*args, **kwargs):
        seen["own_thread"] = threading.current_thread() is not threading.main_thread()
        seen["beside_coherence"] = coherence_started.wait(timeout=30)
        return real_unwrap(*args, **kwargs)

    def flagged_coherence(*args, **kwargs):
        coherence_started.set()
        return real_coherence(*args, **kwargs)

    monkeypatch.setattr(mesh_stage, "unwrap_mesh", waiting_unwrap)
    monkeypatch.setattr(mesh_stage, "coherence", flagged_coherence)
    cfg = MeshConfig(resolution=33, target_faces=0, color="field", coarse_to_fine=False, texture_faces=200, texture_size=64)
    _, out = _run_stage(scene_dir, model, cfg, monkeypatch)

    assert seen == {"own_thread": True, "beside_coherence": True}
    textured = json.loads((out / "mesh_report.json").read_text())["textured"]
    assert not textured.get("failed") and (out / "mesh_textured.glb").is_file()
    assert set(textured["timings_s"]) == {"decimate_s", "unwrap_s", "bake_s", "unwrap_wait_s"}


def test_the_automatic_texture_gives_every_photo_pixel_on_the_surface_a_texel_and_no_more() -> None:
    """mesh.texture_size=0: the smallest automatic side whose texels on the surface (TEXTURE_COVERAGE of them) are at
    least the photo pixels there; the largest one when even it falls short (and it says so); a set size as given."""
    auto = MeshConfig(texture_size=0)
    for area, footprint in ((7.18, 0.00666), (0.5, 0.01), (2.0, 0.003), (7.18, 0.00333)):
        side, why = mesh_plan.texture_side(auto, area, footprint)
        pixels = area / footprint**2
        smaller = [s for s in mesh_plan.AUTO_TEXTURE_SIDES if s < side]
        assert side**2 * mesh_plan.TEXTURE_COVERAGE >= pixels or side == mesh_plan.AUTO_TEXTURE_SIDES[-1]
        assert not smaller or smaller[-1] ** 2 * mesh_plan.TEXTURE_COVERAGE < pixels, (area, footprint, side)
        assert f"texture {side}²" in why and "mesh.texture_size" in why
    assert mesh_plan.texture_side(auto, 7.18, 0.00666)[0] == 1024  # the shipped sample's balanced mesh: 569² wanted
    assert mesh_plan.texture_side(auto, 0.5, 0.01)[0] == 512
    side, why = mesh_plan.texture_side(auto, 7.18, 0.001)
    assert side == 2048 and "largest automatic size" in why
    assert mesh_plan.texture_side(MeshConfig(texture_size=300), 7.18, 0.001)[0] == 300


def test_the_stage_sizes_the_texture_to_the_photos_by_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With mesh.texture_size=0 the stage bakes the side `texture_side` gives for its cleaned mesh's area and the
    photos' footprint, and reports that size and why."""
    model = SoftSphere(amplitude=400.0, width=0.05, samples=64)
    scene_dir = _scene_dir(tmp_path, model, np.eye(4), kind="transforms")
    cfg = MeshConfig(resolution=33, target_faces=0, color="field", coarse_to_fine=False, texture_faces=200, texture_size=0)
    _, out = _run_stage(scene_dir, model, cfg, monkeypatch)
    report = json.loads((out / "mesh_report.json").read_text())
    footprint = report["resolution"]["pixel_footprint"]
    assert footprint is None  # mesh.resolution was given: the grid did not use it, the texture does all the same
    side = report["textured"]["texture_size"]
    assert side in mesh_plan.AUTO_TEXTURE_SIDES and report["textured"]["coverage"] > 0
    assert report["textured"]["texture_size_reason"].startswith(f"texture {side}²: the photos put about")
    assert side == mesh_plan.texture_side(cfg, report["clean"]["output"]["area"], report["resolution"]["photo_footprint"])[0]


@pytest.mark.parametrize("fails", ["unwrap", "export"])
def test_a_failed_textured_mesh_still_delivers_the_vertex_colored_mesh_and_says_why(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], fails: str
) -> None:
    """The textured mesh is optional: xatlas failing, or its export failing half-way, must not fail the stage."""
    model = SoftSphere(amplitude=400.0, width=0.05, samples=64)
    scene_dir = _scene_dir(tmp_path, model, np.eye(4), kind="transforms")
    if fails == "unwrap":
        def broken(*args, **kwargs):
            raise ValueError("xatlas made no UV charts")
        monkeypatch.setattr(mesh_stage, "unwrap_mesh", broken)  # raised in the unwrap's thread, met where it is awaited
    else:
        real_export = mesh_stage.export_textured_mesh

        def broken(*args, **kwargs):  # writes its files, then fails: nothing half-written may be left
            real_export(*args, **kwargs)
            raise OSError("disk full")
        monkeypatch.setattr(mesh_stage, "export_textured_mesh", broken)
    cfg = MeshConfig(resolution=33, target_faces=0, color="field", coarse_to_fine=False, texture_faces=200, texture_size=64)
    summary, out = _run_stage(scene_dir, model, cfg, monkeypatch)

    report = json.loads((out / "mesh_report.json").read_text())
    glb = trimesh.load(out / "mesh.glb", force="mesh", process=False)
    ply = trimesh.load(out / "mesh.ply", process=False)
    assert len(glb.faces) == len(ply.faces) == report["faces"] == summary["faces"] > 100 and ply.visual.kind == "vertex"
    textured = report["textured"]
    error = "ValueError: xatlas made no UV charts" if fails == "unwrap" else "OSError: disk full"
    assert textured["failed"] and textured["error"] == error
    assert "mesh.texture_size" in textured["what_to_do"] and "mesh.texture_faces=0" in textured["what_to_do"]
    assert summary["textured"].startswith("failed")
    assert not list(out.glob("mesh_textured.*")) and not (out / "preview_textured.png").exists()
    assert "preview_textured.png" not in report["previews"]
    said = " ".join(capsys.readouterr().err.split())  # the console wraps long lines
    assert said.count("textured mesh not written") == 1 and error in said


def test_an_object_density_mesh_in_pieces_points_to_the_surface_preset() -> None:
    """Only an object's density mesh with a share of its area outside the largest piece gets the advice, and it
    says how much lies outside; a zero set (already the surface model) and an unbounded scene never do."""
    from recon.plans.mesh import SPLIT_AREA, pieces_advice

    advice = pieces_advice(0.91, zero_set=False, capture="object")
    assert advice.startswith("9% of the mesh's area lies outside its largest piece") and "--preset surface" in advice
    assert pieces_advice(SPLIT_AREA, zero_set=False, capture="object") == ""
    assert pieces_advice(0.5, zero_set=True, capture="object") == ""
    assert pieces_advice(0.5, zero_set=False, capture="unbounded") == ""
    assert pieces_advice(0.5, zero_set=False, capture=None) == ""


class HollowBall(SoftSphere):
    """A radiance field that is only a shell (material between radii 0.45 and R0 round CENTRE), as a field is opaque
    only where the photos look: its inside is empty."""

    def density(self, x: Tensor) -> Tensor:
        r = (x - torch.as_tensor(CENTRE, dtype=x.dtype, device=x.device)).norm(dim=-1)
        return self.amplitude * torch.sigmoid((R0 - r) / self.width) * torch.sigmoid((r - 0.45) / self.width)


def test_a_closed_mesh_is_a_watertight_solid_capped_on_the_ground_the_open_one_is_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = HollowBall(amplitude=3000.0, width=0.004, samples=384)
    base = CENTRE[2] - 0.3
    meshes = {}
    for closed in (False, True):
        scene_dir = _scene_dir(tmp_path / str(closed), model, np.eye(4), kind="transforms")
        doc = json.loads((scene_dir / "02_scene" / "scene.json").read_text())
        doc["ground"] = [0.0, 0.0, 1.0, base]  # it stands on a table through the ball's lower part
        (scene_dir / "02_scene" / "scene.json").write_text(json.dumps(doc))
        cfg = MeshConfig(resolution=97, target_faces=0, color="field", texture_faces=0, closed=closed,
                         ground_margin_cells=0.0)
        summary, out = _run_stage(scene_dir, model, cfg, monkeypatch)
        meshes[closed] = (summary, trimesh.load(out / "mesh.ply", process=False))
        radius = model.radius_at(json.loads((out / "mesh_report.json").read_text())["iso"])
    (open_summary, open_mesh), (closed_summary, solid) = meshes[False], meshes[True]
    assert not open_summary["watertight"]  # open where the table was, its empty inside seen by no photo
    assert closed_summary["watertight"] and solid.is_watertight
    height = radius + 0.3  # the ball above the table: a sphere less its cap below the cut
    below = math.pi * (radius - 0.3) ** 2 * (3 * radius - (radius - 0.3)) / 3
    assert solid.volume == pytest.approx(4 / 3 * math.pi * radius**3 - below, rel=0.03)
    assert solid.vertices[:, 2].min() == pytest.approx(base, abs=2 / 96)
    assert np.ptp(solid.vertices[:, 2]) == pytest.approx(height, abs=2 / 96)
    flat = np.abs(solid.vertices[:, 2] - base) < 1e-3
    assert flat.sum() > 50 and flat.sum() < 0.5 * len(solid.vertices)  # a flat base, and the ball above it
