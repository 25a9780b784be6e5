"""Mesh coherence numbers (recon.geometry.coherence) on cases whose answers are known in closed form."""
from __future__ import annotations

import numpy as np
import pytest

from recon.geometry.coherence import (
    depth_points,
    largest_piece,
    mesh_zbuffers,
    object_pixels,
    point_agreement,
    projected_coverage,
)


def _square(cx: float, cy: float, half: float, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of an axis-aligned square in the plane z, centred at (cx, cy), side 2 * half."""
    v = np.array([[cx - half, cy - half, z], [cx + half, cy - half, z], [cx + half, cy + half, z], [cx - half, cy + half, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _camera_above(height: float = 1.0) -> tuple[np.ndarray, tuple[float, float, float, float], tuple[int, int]]:
    """OpenGL camera at (0, 0, height) looking down -Z (its +Y is world +Y), 100 px square, f = 100 px."""
    c2w = np.eye(4)
    c2w[2, 3] = height
    return c2w, (100.0, 100.0, 50.0, 50.0), (100, 100)


def test_largest_piece_is_the_area_share_of_the_biggest_component():
    v1, f1 = _square(0, 0, 1.0)      # area 4
    v2, f2 = _square(5, 0, 0.5)      # area 1, disjoint
    v3, f3 = _square(9, 0, 0.5)      # area 1
    verts = np.concatenate([v1, v2, v3])
    faces = np.concatenate([f1, f2 + 4, f3 + 8])
    out = largest_piece(verts, faces)
    assert out["pieces"] == 3
    assert out["largest_area_fraction"] == pytest.approx(4 / 6)
    assert largest_piece(v1, f1) == {"pieces": 1, "largest_area_fraction": 1.0}
    assert largest_piece(np.zeros((0, 3)), np.zeros((0, 3), np.int64))["largest_area_fraction"] == 0.0


def test_point_agreement_tells_points_on_the_mesh_from_points_it_hides_and_misses():
    """A square 1 unit below the camera (|x|, |y| <= 0.2): a point on it is on the mesh; a point below it is hidden
    (the mesh lies in front of a surface the photo saw); a point above it, or beside it where no face is, is missed."""
    verts, faces = _square(0, 0, 0.2)
    cam = _camera_above()
    on = [[0.05, 0.05, 0.0], [-0.1, 0.15, -0.005]]  # within the tolerance 0.01 (the second just below)
    hidden = [[0.0, -0.1, -0.2]]  # 0.2 below the square, behind it from the camera
    missed = [[0.1, 0.0, 0.3], [0.35, 0.0, 0.0]]  # in front of the square; beside it
    unseen = [[5.0, 0.0, 0.0], [0.0, 0.0, 2.0]]  # outside the image; behind the camera
    zbuf = mesh_zbuffers(verts, faces, [cam])
    out = point_agreement(zbuf, [cam], [np.array(on + hidden + missed + unseen)], tolerance=0.01)
    assert out["sightings"] == 5
    assert out["on"] == pytest.approx(2 / 5) and out["in_front"] == pytest.approx(1 / 5)
    assert out["missing"] == pytest.approx(2 / 5)
    tight = point_agreement(zbuf, [cam], [np.array(on)], tolerance=0.001)  # 0.005 off: in front now
    assert tight["on"] == pytest.approx(0.5) and tight["in_front"] == pytest.approx(0.5)
    assert point_agreement(zbuf, [cam], [np.array(unseen)], 0.01)["sightings"] == 0
    with pytest.raises(ValueError, match="one point set per camera"):
        point_agreement(zbuf * 2, [cam, cam], [np.array(on)], 0.01)


def test_projected_coverage_counts_object_pixels_the_mesh_covers():
    # the square |x|, |y| <= 0.2 one unit below the camera covers pixel columns/rows 30..69 (40 x 40)
    verts, faces = _square(0, 0, 0.2)
    cam = _camera_above()
    wide = np.zeros((100, 100), bool)
    wide[30:70, 30:90] = True        # the object is 60 px wide, the mesh covers 40 of them
    half = np.zeros((100, 100), bool)
    half[30:70, 30:50] = True        # the object is half the square: the other half of the mesh is outside it
    out = projected_coverage(mesh_zbuffers(verts, faces, [cam, cam]), [wide, half])
    assert out["views"][0]["coverage"] == pytest.approx(40 * 40 / (40 * 60))
    assert out["views"][0]["outside"] == 0.0
    assert out["views"][1]["coverage"] == 1.0
    assert out["views"][1]["outside"] == pytest.approx(0.5)
    assert out["coverage"] == pytest.approx((1600 + 800) / (2400 + 800))
    assert out["outside"] == pytest.approx(800 / 3200)
    with pytest.raises(ValueError, match="one object mask per camera"):
        projected_coverage(mesh_zbuffers(verts, faces, [cam]), [])


def test_object_pixels_from_rendered_depth_match_the_mesh_of_the_object():
    # a ground plane z = 0 seen from above; the object region is the box |x|, |y| <= 0.2: its pixels are
    # exactly the pixels the square mesh of that region covers (coverage 1, nothing outside)
    c2w, intr, hw = _camera_above(2.0)
    h, w = hw
    j, i = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    depth = 2.0 * np.sqrt(1 + ((i - 50) / 100) ** 2 + ((j - 50) / 100) ** 2)  # ray distance to z = 0
    pts = depth_points(c2w, intr, depth)
    assert np.abs(pts[..., 2]).max() < 1e-9

    def inside(p: np.ndarray) -> np.ndarray:
        return (np.abs(p[:, 0]) <= 0.2) & (np.abs(p[:, 1]) <= 0.2) & (np.abs(p[:, 2]) <= 0.1)

    obj = object_pixels(c2w, intr, depth, inside)
    assert obj.sum() == 20 * 20      # 0.4 units at distance 2 = 20 px
    verts, faces = _square(0, 0, 0.2)
    out = projected_coverage(mesh_zbuffers(verts, faces, [(c2w, intr, hw)]), [obj])
    assert out["coverage"] == 1.0 and out["outside"] == 0.0
    far = np.full(hw, np.inf)        # a transparent view: nothing is object
    assert not object_pixels(c2w, intr, far, inside).any()


def test_mesh_stage_coherence_uses_masks_or_the_region_above_the_ground():
    from recon.evaluation.views import View
    from recon.meshing.photos import coherence

    c2w, intr, hw = _camera_above(2.0)
    h, w = hw
    j, i = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    depth = 2.0 * np.sqrt(1 + ((i - 50) / 100) ** 2 + ((j - 50) / 100) ** 2)  # the table z = 0 everywhere
    depth[30:50, 30:50] *= 0.75  # a box top at z = 0.5 over x in [-0.3, 0], y in [0, 0.3] (1.5 below the camera)
    image = np.zeros((h, w, 4), np.uint8)
    image[30:50, 30:70, 3] = 255  # the mask calls twice the box's footprint object
    view = View("a", image, c2w, intr, 0.1, 10.0)
    top, faces = _square(-0.15, 0.15, 0.15, z=0.5)  # the box top: pixel rows and columns 30..49
    table, _ = _square(0, 0, 0.9, z=0.0)
    verts = np.concatenate([top, table])
    both = np.concatenate([faces, faces + 4])
    region = np.array([[-0.5, -0.5, -0.1], [0.5, 0.5, 1.0]])
    ground = np.array([0.0, 0.0, 1.0, 0.0])
    # without masks: the object is what lies in the region above the ground: the box top; the table is not
    out = coherence(top, faces, [view], [depth], region, ground, 0.05, masked=False)
    assert out["largest_piece"] == {"pieces": 1, "largest_area_fraction": 1.0}
    assert out["projected"]["object_pixels"] == 400
    assert out["projected"]["coverage"] == 1.0 and out["projected"]["outside"] == 0.0
    with_table = coherence(verts, both, [view], [depth], region, ground, 0.05, masked=False)
    assert with_table["largest_piece"]["largest_area_fraction"] == pytest.approx(3.24 / (3.24 + 0.09))
    assert with_table["projected"]["outside"] == pytest.approx(1 - 400 / (90 * 90))  # the table: pixels 5..94
    # with masks: the masks decide (800 object pixels, the box top covers half)
    masked = coherence(top, faces, [view], [depth], region, ground, 0.05, masked=True)
    assert masked["projected"]["coverage"] == pytest.approx(0.5) and masked["projected"]["outside"] == 0.0
    assert coherence(top, faces, [], [], region, ground, 0.05, masked=False)["projected"] is None
    # SfM points: only those in the region above the ground count; one on the box top, one on the table (cut)
    seen = [np.array([[-0.1, 0.1, 0.5], [0.4, -0.4, 0.0]])]
    agree = coherence(top, faces, [view], [depth], region, ground, 0.05, masked=False, seen_points=seen,
                      point_tolerance=0.02)["points"]
    assert agree["sightings"] == 1 and agree["on"] == 1.0


def test_transparent_pixels_are_not_object_when_the_region_is_the_scene_box():
    """A transparent ray's rendered depth is its exit from the scene box (the models put the remainder there), which
    lies on the region's boundary when the region is the box: only the field's opacity tells it from a surface."""
    from recon.evaluation.views import View
    from recon.meshing.photos import coherence

    c2w, intr, hw = _camera_above(2.0)
    h, w = hw
    j, i = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    stretch = np.sqrt(1 + ((i - 50) / 100) ** 2 + ((j - 50) / 100) ** 2)
    region = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 1.0]])  # the box: rays leave it through z = -0.5
    depth = 2.5 * stretch
    opacity = np.zeros(hw)
    depth[30:50, 30:50] = 1.5 * stretch[30:50, 30:50]  # an opaque box top at z = 0.5
    opacity[30:50, 30:50] = 1.0
    top, faces = _square(-0.15, 0.15, 0.15, z=0.5)
    view = View("a", np.zeros((h, w, 3), np.uint8), c2w, intr, 0.1, 10.0)
    exits = object_pixels(c2w, intr, depth, lambda p: np.all((p >= region[0] - 1e-9) & (p <= region[1] + 1e-9), axis=1))
    assert exits.sum() > 400  # without the opacity the box's far face reads as object
    out = coherence(top, faces, [view], [depth], region, None, 0.05, masked=False, opacities=[opacity])
    assert out["projected"]["object_pixels"] == 400
    assert out["projected"]["coverage"] == 1.0
