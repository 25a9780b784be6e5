"""clean_mesh: crop to the scene box, floater removal by area, Taubin smoothing, decimation, report."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from recon.geometry.clean import (
    clean_mesh,
    component_areas,
    decimate_closed,
    remove_duplicate_faces,
    split_pinched_edges,
)

AABB = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def sphere(radius: float, center=(0.0, 0.0, 0.0), subdivisions: int = 4) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(center)
    return mesh


def scene_with_floaters() -> trimesh.Trimesh:
    """Main ball r=0.5 plus a floater ball r=0.05 (1 % of its area) and a ball outside the box."""
    return trimesh.util.concatenate([sphere(0.5), sphere(0.05, (0.8, 0.0, 0.0), 2), sphere(0.1, (0.0, 0.0, 1.5), 2)])


def test_crop_and_floater_removal_keep_only_the_main_object():
    mesh = scene_with_floaters()
    verts, faces, report = clean_mesh(mesh.vertices, mesh.faces, AABB, min_component_fraction=0.05)
    main = sphere(0.5)
    assert len(verts) == len(main.vertices) and len(faces) == len(main.faces)
    assert np.allclose(np.linalg.norm(verts, axis=1), 0.5)
    assert report["components"]["components"] == 2  # the outside ball is cropped before counting
    assert report["components"]["removed"] == 1
    assert "0.05" in report["components"]["rule"]
    assert report["cropped"]["faces"] == len(mesh.faces) - len(sphere(0.1, subdivisions=2).faces)
    assert report["output"]["watertight"]
    np.testing.assert_allclose(report["output"]["bbox"], [[-0.5] * 3, [0.5] * 3], atol=1e-6)
    assert verts.dtype == np.float32 and faces.dtype == np.int64


def test_small_fraction_keeps_floater_and_crop_cuts_open_surface():
    mesh = scene_with_floaters()
    _, faces, report = clean_mesh(mesh.vertices, mesh.faces, AABB, min_component_fraction=0.001)
    assert report["components"]["removed"] == 0
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 0.25]])  # cuts the main ball: no longer closed
    _, _, cut = clean_mesh(mesh.vertices, mesh.faces, box)
    assert not cut["output"]["watertight"] and cut["output"]["bbox"][1][2] <= 0.25


def test_what_the_photos_see_of_an_inner_wall_is_removed_as_crumbs_after_the_hidden_faces():
    """An inner wall (a ball a quarter of the outer's area, so the floater rule keeps it) of which the photos see
    only a small cap, as they see a fast field's walls through its soft shell: removing the faces no photo sees
    leaves the cap, a crumb the floater rule then removes; with the rule off it stays."""
    mesh = trimesh.util.concatenate([sphere(0.5), sphere(0.25)])

    def seen(vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:  # the outer ball, and the inner's top cap
        r = np.linalg.norm(vertices, axis=1)
        return (r > 0.4) | (vertices[:, 2] > 0.24)

    verts, faces, report = clean_mesh(mesh.vertices, mesh.faces, AABB, min_component_fraction=0.05, seen_fn=seen)
    assert report["components"]["removed"] == 0 and report["hidden"]["removed_faces"] > 0
    assert report["crumbs"]["components"] == 2 and report["crumbs"]["removed"] == 1
    assert len(faces) == len(sphere(0.5).faces) and np.allclose(np.linalg.norm(verts, axis=1), 0.5)
    _, faces_kept, kept = clean_mesh(mesh.vertices, mesh.faces, AABB, min_component_fraction=0.0, seen_fn=seen)
    assert kept["crumbs"]["removed"] == 0 and len(faces_kept) > len(faces)


def test_component_areas_sum_to_total_area():
    mesh = scene_with_floaters()
    labels, areas = component_areas(mesh)
    assert len(areas) == 3 and labels.shape == (len(mesh.faces),)
    assert areas.sum() == pytest.approx(mesh.area)


def test_taubin_smoothing_removes_noise_without_shrinking():
    rng = np.random.default_rng(0)
    mesh = sphere(0.5, subdivisions=4)
    noisy = mesh.vertices * (1 + rng.normal(0, 0.01, (len(mesh.vertices), 1)))
    _, _, plain = clean_mesh(noisy, mesh.faces, AABB)
    verts, _, report = clean_mesh(noisy, mesh.faces, AABB, smooth_iters=10)
    r0 = np.linalg.norm(noisy, axis=1)
    r1 = np.linalg.norm(verts, axis=1)
    assert r1.std() < 0.5 * r0.std()  # the bumps are flattened
    assert abs(r1.mean() - 0.5) < 0.005  # but the ball keeps its size (Laplacian would shrink it)
    assert report["smoothed"]["iterations"] == 10 and "smoothed" not in plain


def test_decimation_hits_target_and_keeps_shape():
    mesh = sphere(0.5, subdivisions=5)  # 20480 faces
    verts, faces, report = clean_mesh(mesh.vertices, mesh.faces, AABB, target_faces=2000)
    assert 1800 <= len(faces) <= 2000
    assert report["decimated"]["faces"] == len(faces) and report["input"]["faces"] == 20480
    assert np.abs(np.linalg.norm(verts, axis=1) - 0.5).max() < 0.01
    assert trimesh.Trimesh(verts, faces).is_watertight


def test_duplicate_vertices_are_merged_and_empty_crop_is_reported():
    mesh = sphere(0.3, subdivisions=2)
    soup = mesh.triangles.reshape(-1, 3)  # every face with its own 3 vertices
    verts, faces, report = clean_mesh(soup, np.arange(len(soup)).reshape(-1, 3), AABB)
    assert len(verts) == len(mesh.vertices) and report["merged"]["vertices"] == len(mesh.vertices)
    far = np.array([[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]])
    verts, faces, report = clean_mesh(mesh.vertices, mesh.faces, far)
    assert len(faces) == 0 and report["output"]["faces"] == 0 and report["components"]["components"] == 0


def test_duplicate_faces_fins_cancel_and_copies_collapse():
    tet = trimesh.creation.icosphere(subdivisions=0)  # closed, 20 faces
    faces = np.asarray(tet.faces)
    fin = np.vstack([faces, [[0, 1, 2], [2, 1, 0]]])  # a zero-volume fin: both windings of one triangle
    out, removed = remove_duplicate_faces(fin)
    assert removed == 2 and np.array_equal(out, faces)
    copy = np.vstack([faces, faces[3:4][:, [1, 2, 0]]])  # same face again, rotated: same winding
    out, removed = remove_duplicate_faces(copy)
    assert removed == 1 and np.array_equal(out, faces)
    assert trimesh.Trimesh(tet.vertices, out).is_watertight


def test_a_zero_area_face_marching_cubes_leaves_in_a_closed_mesh_keeps_it_closed() -> None:
    """A tetrahedron whose edge AB is split by its midpoint M on one side only: the zero-area face (A, M, B) with three
    distinct vertices closes it. Dropping it (as an area test would) opens a three-edge hole."""
    from recon.geometry.clean import _mesh

    v = np.array([[0.0, 0, 0], [2, 0, 0], [1, 2, 0], [1, 1, 2], [1, 0, 0]])  # A, B, C, D, M = (A + B) / 2
    faces = np.array([[0, 4, 2], [4, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0], [0, 1, 4]])  # AMC, MBC, ADB, BDC, CDA, ABM
    faces[:, [1, 2]] = faces[:, [2, 1]]  # any consistent winding; watertightness does not depend on it
    mesh = _mesh(v, faces)
    assert len(mesh.faces) == 6 and mesh.is_watertight
    collapsed = _mesh(np.concatenate([v, v[:1]]), np.concatenate([faces, [[0, 5, 3]]]))  # vertex 5 merges into 0
    assert len(collapsed.faces) == 6 and collapsed.is_watertight  # the face merging collapsed is dropped


def test_two_sheets_pinched_on_one_edge_are_parted_and_the_mesh_is_watertight_again() -> None:
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 1, 1))
    b.apply_translation((1.0, 1.0, 0.0))  # touches the first cube along one edge only
    pinched = trimesh.util.concatenate([a, b])
    pinched.merge_vertices()  # the edge's two vertices are shared: four faces on one edge
    assert not pinched.is_watertight
    parted, made = split_pinched_edges(pinched)
    assert parted.is_watertight and made >= 1 and parted.volume == pytest.approx(2.0, rel=1e-3)
    again = parted.copy()
    again.merge_vertices()  # a tool that merges coincident vertices does not pinch it again
    assert again.is_watertight
    fine_a, fine_b = a.subdivide().subdivide(), b.subdivide().subdivide()  # the pinch is a chain of four edges
    chained = trimesh.util.concatenate([fine_a, fine_b])
    chained.merge_vertices()
    assert not chained.is_watertight
    parted, made = split_pinched_edges(chained)
    assert parted.is_watertight and made >= 4 and parted.volume == pytest.approx(2.0, rel=1e-3)


def test_a_closed_mesh_stays_watertight_through_decimation() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=5)
    out, _, tries = decimate_closed(sphere, 2000)
    assert out.is_watertight and tries >= 1 and len(out.faces) <= 2100
