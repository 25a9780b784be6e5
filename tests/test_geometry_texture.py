"""The textured mesh: UV unwrap, texel → surface point, seam padding, and the exported files, against closed
forms and an analytic color; then baking from photos of an analytic field (rendered with the project's own
renderer from known cameras), measured in held-out views against the vertex-colored mesh."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from recon.app.progress import Reporter
from recon.camera import look_at, project
from recon.config import MeshConfig
from recon.evaluation.views import View, render_view
from recon.geometry.export import Z_UP_TO_Y_UP, export_textured_mesh
from recon.geometry.raster import interpolate, rasterize, render_mesh
from recon.geometry.texture import XATLAS_AREA_EPSILON, make_textured_mesh, pad_texture, texel_samples, unwrap
from recon.meshing.extraction import extract_mesh
from recon.meshing.photos import bake_colors, compare_in_views, mesh_depths, texture_mesh
from tests.analytic_sphere import AABB, BACKGROUND, CENTRE, SoftSphere, run_mesh_stage, write_scene_dir


def smooth_color(p: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """A smooth analytic color of 3D points (N, 3) → (N, 3) in [0.1, 0.9]."""
    return 0.5 + 0.4 * np.sin(np.stack([2 * p[:, 0], 3 * p[:, 1] + 1, 2.5 * p[:, 2] - 1], axis=1))


def uv_area(uv: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = uv[faces[:, 0]], uv[faces[:, 1]], uv[faces[:, 2]]
    return float(0.5 * np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])).sum())


# ---------------------------------------------------------------------------------------- library
def test_unwrap_keeps_faces_and_makes_non_overlapping_charts() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    source, faces, uv = unwrap(sphere.vertices, sphere.faces, 256)
    assert faces.shape == sphere.faces.shape and len(source) == len(uv) >= len(sphere.vertices)
    np.testing.assert_array_equal(source[faces], sphere.faces)  # same faces, same order; seams split vertices
    assert uv.min() >= 0 and uv.max() <= 1
    mask, points, _ = texel_samples(sphere.vertices[source], faces, uv, sphere.vertex_normals[source], (256, 256))
    # charts do not overlap: the texels covered match the charts' total UV area (up to their edges)
    assert mask.mean() == pytest.approx(uv_area(uv, faces), rel=0.1)
    assert np.abs(np.linalg.norm(points, axis=1) - 1).max() < 0.02  # texel points lie on the (inscribed) sphere


def test_unwrap_does_not_depend_on_the_mesh_scale() -> None:
    """xatlas leaves out faces of area <= float32 eps in absolute units (a small object or a dense mesh: all of
    them, and no atlas at all); unwrap scales the mesh first, so a millimetre sphere unwraps like a metre one."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    small = sphere.vertices * 1e-3 + [5.0, -3.0, 2.0]
    assert trimesh.Trimesh(small, sphere.faces, process=False).area_faces.max() < XATLAS_AREA_EPSILON  # every face
    source, faces, uv = unwrap(sphere.vertices, sphere.faces, 64)
    small_source, small_faces, small_uv = unwrap(small, sphere.faces, 64)
    np.testing.assert_array_equal(small_source[small_faces], sphere.faces)
    assert uv_area(uv, faces) > 0.1 and uv_area(small_uv, small_faces) == pytest.approx(uv_area(uv, faces), rel=0.02)
    assert len(np.unique(small_uv.round(6), axis=0)) > 0.9 * len(small_uv)  # no face collapsed to one UV point


def test_unwrap_of_a_mesh_without_area_says_so_and_a_small_texture_still_unwraps() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    for faces in (sphere.faces[:0], np.repeat(sphere.faces[:, :1], 3, axis=1)):
        with pytest.raises(ValueError, match="without faces|none of its"):
            unwrap(sphere.vertices, faces, 64)
    with pytest.raises(ValueError, match="none of its 1,280 faces"):
        unwrap(np.full_like(sphere.vertices, np.nan), sphere.faces, 64)
    # far more charts than a 16² texture has texels: still one atlas (xatlas packs its own resolution)
    bumpy = sphere.vertices * (1 + 0.05 * np.random.default_rng(0).standard_normal((len(sphere.vertices), 1)))
    source, faces, uv = unwrap(bumpy, sphere.faces, 16)
    np.testing.assert_array_equal(source[faces], sphere.faces)
    assert 0 <= uv.min() and uv.max() <= 1


def test_texel_samples_on_a_flat_quad_are_the_texel_centres() -> None:
    vertices = np.array([[0.0, 0.0, 0.5], [2.0, 0.0, 0.5], [2.0, 1.0, 0.5], [0.0, 1.0, 0.5]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # u = x / 2, v = y
    normals = np.tile([0.0, 0.0, 3.0], (4, 1))
    mask, points, nrm = texel_samples(vertices, np.array([[0, 1, 2], [0, 2, 3]]), uv, normals, (8, 16))
    assert mask.all()
    rows, cols = np.nonzero(mask)
    u, v = (cols + 0.5) / 16, 1 - (rows + 0.5) / 8  # row 0 is the top of the image: v near 1
    np.testing.assert_allclose(points, np.stack([2 * u, v, np.full_like(u, 0.5)], axis=1), atol=1e-12)
    np.testing.assert_allclose(nrm, np.tile([0.0, 0.0, 1.0], (len(nrm), 1)))


def test_padding_copies_the_nearest_island_texel() -> None:
    texture = np.zeros((12, 12, 3), np.float32)
    mask = np.zeros((12, 12), bool)
    mask[2:4, 2:4], texture[2:4, 2:4] = True, [1.0, 0.0, 0.0]
    mask[8:10, 8:10], texture[8:10, 8:10] = True, [0.0, 0.0, 1.0]
    padded, filled = pad_texture(texture, mask, texels=2)
    np.testing.assert_array_equal(padded[mask], texture[mask])  # islands untouched
    np.testing.assert_array_equal(padded[1, 1], [1, 0, 0])  # diagonal neighbour, distance √2
    np.testing.assert_array_equal(padded[4, 3], [1, 0, 0])
    np.testing.assert_array_equal(padded[10, 9], [0, 0, 1])
    assert not filled[6, 6] and np.all(padded[6, 6] == 0)  # farther than 2 texels from both: left alone
    everything, filled_all = pad_texture(texture, mask)
    assert filled_all.all() and np.all(everything.max(axis=-1) == 1.0)
    np.testing.assert_array_equal(everything[0, 6], [1, 0, 0])  # d² = 13 to red, 68 to blue
    np.testing.assert_array_equal(everything[11, 11], [0, 0, 1])


def test_baked_texture_renders_the_analytic_color_and_survives_export(tmp_path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    textured = make_textured_mesh(sphere.vertices, sphere.faces, 2000, 256, smooth_color)
    assert textured.info["faces"] <= 2000 and textured.texture.shape == (256, 256, 3)
    # seen from a camera, each pixel's texture color is the analytic color of the surface point under it
    c2w = look_at(np.array([0.3, -2.5, 1.0]), np.zeros(3))
    intr, hw = (80.0, 80.0, 48.0, 48.0), (96, 96)
    rgb, mask = render_mesh(textured.vertices, textured.faces, c2w, intr, hw, uv=textured.uv, texture=textured.texture)
    face_id, bary, _ = rasterize(*project(textured.vertices, c2w, np.array(intr)), textured.faces, hw)
    surface = interpolate(textured.vertices, textured.faces, face_id, bary)[mask]
    err = np.abs(rgb[mask] - smooth_color(surface)).max(axis=1)
    assert mask.sum() > 1500 and np.percentile(err, 99) < 0.03  # texel size ≈ 0.01 units, 8-bit rounding
    # no seam lines: the worst pixel is still close (an unpadded seam would read black texels, error ≈ 0.5)
    assert err.max() < 0.08

    # glb and obj: reloaded by trimesh, they render the same image (glb/obj are +Y up: rotate the camera too)
    paths = export_textured_mesh(textured.vertices, textured.faces, textured.uv, textured.texture, tmp_path,
                                 normals=textured.normals)
    assert {p.name for p in paths.values()} == {"mesh_textured.glb", "mesh_textured.obj", "mesh_textured.mtl", "mesh_textured.png"}
    assert "map_Kd mesh_textured.png" in paths["mtl"].read_text() and "mtllib mesh_textured.mtl" in paths["obj"].read_text()
    assert paths["png"].read_bytes() in paths["glb"].read_bytes()  # the glb embeds the one PNG encoding as it is
    for fmt in ("glb", "obj"):
        mesh = trimesh.load(paths[fmt], force="mesh", process=False)
        assert isinstance(mesh.visual, trimesh.visual.TextureVisuals)
        image = mesh.visual.material.baseColorTexture if fmt == "glb" else mesh.visual.material.image
        assert image.size == (256, 256)
        tex = np.asarray(image.convert("RGB"))
        again, mask2 = render_mesh(mesh.vertices, mesh.faces, Z_UP_TO_Y_UP @ c2w, intr, hw, uv=mesh.visual.uv, texture=tex)
        assert (mask2 != mask).mean() < 0.002, fmt
        both = mask & mask2
        assert np.abs(again[both] - rgb[both]).max() < 1e-3 + 2 / 255, fmt  # obj stores 8 digits, png is lossless


# ---------------------------------------------------------------------------------------- baking from photos
class StripedSphere(SoftSphere):
    """The analytic soft sphere with stripes finer than a decimated mesh's vertex spacing."""

    def radiance(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        p = x - torch.as_tensor(CENTRE, dtype=x.dtype)
        az = torch.atan2(p[:, 1], p[:, 0])
        el = torch.asin((p[:, 2] / p.norm(dim=-1).clamp_min(1e-9)).clamp(-1, 1))
        s = torch.sin(9 * az) * torch.cos(7 * el)
        return torch.stack([0.5 + 0.35 * s, 0.5 - 0.3 * s, 0.4 + 0.2 * torch.cos(5 * el)], dim=-1)


def photos(model: SoftSphere, angles: list[tuple[float, float]], size: int = 64) -> list[View]:
    """Photos of the field rendered by the project's renderer from cameras at distance 3 at (azimuth,
    elevation) degrees, looking at the origin."""
    views = []
    for k, (az, el) in enumerate(angles):
        a, e = math.radians(az), math.radians(el)
        eye = 3.0 * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
        view = View(f"p{k:02d}", np.zeros((size, size, 3), np.uint8), look_at(eye, np.zeros(3)), (2.0 * size, 2.0 * size, size / 2, size / 2), 0.0, 0.0)
        rgb = render_view(model, view, torch.tensor(AABB, dtype=torch.float32), BACKGROUND)["rgb"]
        view.image[:] = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        views.append(view)
    return views


def test_texture_baked_from_photos_matches_held_out_photos_and_fills_what_no_photo_sees() -> None:
    model = StripedSphere(amplitude=3000.0, width=0.004, samples=192)
    # training photos from above only (elevation 15° to 50°): the bottom of the sphere is never seen
    train = photos(model, [(360 * i / 8, 15 + 35 * (i % 2)) for i in range(8)])
    held_out = photos(model, [(18.0, 30.0), (200.0, 25.0)])
    aabb_t = torch.tensor(AABB, dtype=torch.float32)
    quiet = Reporter(quiet=True)
    vertices, faces, _ = extract_mesh(model, aabb_t, (97, 97, 97), MeshConfig(), quiet)
    depths = mesh_depths(vertices, faces, train)  # occlusion by the mesh itself, as the stage bakes
    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    fill = torch.tensor([0.9, 0.1, 0.9])
    model.radiance = lambda x, d: fill.expand(x.shape[0], 3)  # type: ignore[method-assign]  # the field's fill color
    colors, _ = bake_colors(model, train, depths, vertices, normals)

    cfg = MeshConfig(texture_faces=1500, texture_size=256)
    textured = texture_mesh(model, cfg, train, depths, vertices, faces, quiet, cfg.texture_size)
    assert textured.info["faces"] <= 1500 and textured.info["unseen_from_field"] > 0
    # vertex colors on the same 1500-face mesh: what the texture replaces
    low_colors, _ = bake_colors(model, train, depths, textured.vertices, textured.normals)

    dense, strips = compare_in_views(held_out, BACKGROUND, (vertices, faces, colors), textured, quiet, low_colors)
    tex_db, dense_db, coarse_db = dense["psnr_textured_covered"], dense["psnr_vertex_colors_covered"], dense["psnr_light_vertex_colors_covered"]
    assert tex_db > dense_db - 1.0  # 1.5k faces + 256² texels ≈ the colors of the 33k-face mesh
    assert tex_db > coarse_db + 3.0  # and far better than vertex colors on the same light mesh
    assert len(dense["views"]) == 2 and strips[0].shape == (64, 3 * 64 + 8, 3)

    # texels: every island texel has a color (photo or the field's fill), never the black of an unbaked texel
    tex = textured.texture.astype(np.float64) / 255
    island = tex[textured.mask]
    assert np.all(island.max(axis=1) > 0.05)
    is_fill = np.all(np.abs(island - fill.numpy()) < 1.5 / 255, axis=1)
    mask, points, _ = texel_samples(textured.vertices, textured.faces, textured.uv, textured.normals, (256, 256))
    assert is_fill.sum() == pytest.approx(textured.info["unseen_from_field"], abs=2)
    assert np.mean(points[is_fill][:, 2] < CENTRE[2]) > 0.98  # the fill is on the unseen underside
    # padding: texels just outside the islands copy a neighbour (no black rim for bilinear lookups at seams)
    ring = ~textured.mask & (np.pad(textured.mask, 1)[2:, 1:-1] | np.pad(textured.mask, 1)[:-2, 1:-1]
                             | np.pad(textured.mask, 1)[1:-1, 2:] | np.pad(textured.mask, 1)[1:-1, :-2])
    assert ring.sum() > 100 and np.all(tex[ring].max(axis=1) > 0.05)


def test_mesh_stage_writes_the_textured_mesh_and_compares_it_in_the_held_out_views(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = SoftSphere(amplitude=3000.0, width=0.004, samples=192)
    scene_dir = write_scene_dir(tmp_path, model, np.eye(4), kind="transforms")
    scene_json = scene_dir / "02_scene" / "scene.json"
    doc = json.loads(scene_json.read_text())
    for frame in doc["frames"][::3]:
        frame["split"] = "test"  # 2 of the 6 photos held out
    scene_json.write_text(json.dumps(doc))
    cfg = MeshConfig(resolution=49, target_faces=4000, texture_faces=800, texture_size=128)
    summary, out = run_mesh_stage(scene_dir, model, cfg, monkeypatch)
    textured = json.loads((out / "mesh_report.json").read_text())["textured"]
    assert textured["faces"] <= 800 and textured["texture_size"] == 128
    assert sorted(textured["files"].values()) == ["mesh_textured.glb", "mesh_textured.mtl", "mesh_textured.obj", "mesh_textured.png"]
    held = textured["held_out"]
    assert [v["view"] for v in held["views"]] == ["v00", "v03"]
    # the sphere's color is smooth: 800 faces with a texture render it as well as the dense vertex colors
    assert abs(held["psnr_textured_covered"] - held["psnr_vertex_colors_covered"]) < 1.0
    assert "held-out PSNR" in summary["textured"]
    glb = trimesh.load(out / "mesh_textured.glb", force="mesh", process=False)
    assert glb.visual.material.baseColorTexture.size == (128, 128) and len(glb.faces) == textured["faces"]
    for name in ("preview_textured.png", "texture_compare.png"):
        assert (out / name).stat().st_size > 0


def test_a_crash_in_the_unwrap_process_is_an_error_not_the_end_of_the_run() -> None:
    """xatlas segfaults on some meshes: it runs in a process of its own, and its death is a RuntimeError the mesh
    stage turns into a skipped textured copy."""
    import pytest

    from recon.geometry.atlas_child import in_child

    with pytest.raises(RuntimeError, match="signal 11"):
        in_child("crash")
