"""The numpy rasterizer against closed forms: pixel coverage of a triangle and a quad, depth order of two
quads, perspective-correct UV (and color) interpolation with a checker texture."""
from __future__ import annotations

import numpy as np
import pytest

from recon.geometry.raster import interpolate, rasterize, render_mesh, uv_to_pixels

QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def test_triangle_covers_the_pixel_centres_inside_it() -> None:
    xy = np.array([[0.0, 0.0], [8.0, 0.0], [0.0, 8.0]])
    face_id, bary, depth = rasterize(xy, None, np.array([[0, 1, 2]]), (10, 12))
    j, i = np.mgrid[0:10, 0:12]
    inside = (i + 0.5) + (j + 0.5) <= 8.0  # centres on the hypotenuse count
    np.testing.assert_array_equal(face_id >= 0, inside)
    assert inside.sum() == 36
    # barycentric weights at a centre: (1 - x/8 - y/8, x/8, y/8)
    np.testing.assert_allclose(bary[2, 3], [1 - 3.5 / 8 - 2.5 / 8, 3.5 / 8, 2.5 / 8], atol=1e-12)
    assert np.all(depth[inside] == 1.0) and np.all(np.isinf(depth[~inside]))
    # winding does not matter
    flipped, _, _ = rasterize(xy, None, np.array([[0, 2, 1]]), (10, 12))
    np.testing.assert_array_equal(flipped >= 0, inside)


def test_quad_covers_its_pixels_once_without_seam_gaps() -> None:
    xy = np.array([[2.0, 3.0], [7.0, 3.0], [7.0, 9.0], [2.0, 9.0]])
    face_id, bary, _ = rasterize(xy, None, QUAD, (12, 10))
    expected = np.zeros((12, 10), bool)
    expected[3:9, 2:7] = True  # centres 2.5..6.5 × 3.5..8.5
    np.testing.assert_array_equal(face_id >= 0, expected)
    assert set(np.unique(face_id[expected])) == {0, 1}
    np.testing.assert_allclose(bary[expected].sum(axis=1), 1.0)
    # interpolating the vertices' pixel coordinates gives back each pixel centre
    centres = interpolate(xy, QUAD, face_id, bary)
    j, i = np.nonzero(expected)
    np.testing.assert_allclose(centres[expected], np.stack([i + 0.5, j + 0.5], axis=1), atol=1e-12)


def _quad(x0: float, x1: float, y0: float, y1: float, z: float) -> np.ndarray:
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_quad_hides_the_farther_one(near_first: bool) -> None:
    near = _quad(-0.5, 0.5, -0.5, 0.5, -2.0)  # camera at the origin looking down -Z (identity c2w)
    far = _quad(-2.0, 2.0, -2.0, 2.0, -4.0)
    quads = [near, far] if near_first else [far, near]
    vertices = np.concatenate(quads)
    faces = np.concatenate([QUAD, QUAD + 4])
    red, blue = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    colors = np.repeat(np.stack([red, blue] if near_first else [blue, red]), 4, axis=0)
    rgb, mask = render_mesh(vertices, faces, np.eye(4), (20.0, 20.0, 20.0, 20.0), (40, 40), colors=colors, background=(0, 1, 0))
    # near quad → pixels [15, 25)², far quad → [10, 30)²
    is_red = np.all(rgb == red, axis=-1)
    is_blue = np.all(rgb == blue, axis=-1)
    assert is_red.sum() == 100 and is_red[15:25, 15:25].all()
    assert is_blue.sum() == 400 - 100 and is_blue[10:30, 10:30].sum() == 300
    assert mask.sum() == 400 and np.all(rgb[~mask] == [0, 1, 0])
    _, _, depth = rasterize(*_project_identity(vertices), faces, (40, 40))
    np.testing.assert_allclose(depth[20, 20], 2.0)
    np.testing.assert_allclose(depth[12, 12], 4.0)


def _project_identity(vertices: np.ndarray, f: float = 20.0, c: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    z = -vertices[:, 2]
    return np.stack([c + f * vertices[:, 0] / z, c - f * vertices[:, 1] / z], axis=1), z


def test_uv_is_perspective_correct_on_a_tilted_quad_and_samples_a_checker() -> None:
    # the plane z = -4 - x, seen from the origin: its left edge at depth 3, its right edge at depth 5
    vertices = np.array([[-1.0, -1.0, -3.0], [1.0, -1.0, -5.0], [1.0, 1.0, -5.0], [-1.0, 1.0, -3.0]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    f, c, size = 80.0, 64.0, 128
    face_id, bary, depth = rasterize(*_project_identity(vertices, f, c), QUAD, (size, size))
    hit = face_id >= 0
    assert hit.sum() > 1000
    # closed form: the ray through pixel centre (i, j) hits the plane at t = 4 / (1 - dx)
    j, i = np.nonzero(hit)
    dx, dy = (i + 0.5 - c) / f, -(j + 0.5 - c) / f
    t = 4.0 / (1.0 - dx)
    x, y = t * dx, t * dy
    truth = np.stack([(x + 1) / 2, (y + 1) / 2], axis=1)
    got = interpolate(uv, QUAD, face_id, bary)[hit]
    np.testing.assert_allclose(got, truth, atol=1e-9)
    np.testing.assert_allclose(depth[hit], t, rtol=1e-9)
    # screen-space (affine) interpolation would be off by several texels of a 32² texture here
    xy, _ = _project_identity(vertices, f, c)
    affine = interpolate(uv, QUAD, *rasterize(xy, None, QUAD, (size, size))[:2])[hit]
    assert np.abs(affine - truth).max() > 0.03

    # a 32² checker of 4×4-texel squares, sampled bilinearly: exact away from the squares' edges
    checker = ((np.arange(32)[:, None] // 4 + np.arange(32)[None] // 4) % 2).astype(np.uint8) * 255
    texture = np.repeat(checker[..., None], 3, axis=2)
    rgb, mask = render_mesh(vertices, QUAD, np.eye(4), (f, f, c, c), (size, size), uv=uv, texture=texture)
    np.testing.assert_array_equal(mask, hit)
    px = uv_to_pixels(truth, (32, 32))  # texel coordinates; top row of the image is v = 1
    away = np.all(np.abs(px / 4 - np.round(px / 4)) * 4 > 0.5 + 1e-6, axis=1)
    expected = ((px[:, 1] // 4 + px[:, 0] // 4) % 2)[away]
    assert away.sum() > 500
    np.testing.assert_allclose(rgb[hit][away, 0], expected, atol=1e-9)
    # vertex colors take the same perspective-correct weights
    rgb_c, _ = render_mesh(vertices, QUAD, np.eye(4), (f, f, c, c), (size, size), colors=np.c_[uv, np.zeros(4)])
    np.testing.assert_allclose(rgb_c[hit][:, :2], truth, atol=1e-9)


def test_triangles_behind_the_camera_are_dropped_and_empty_input_is_empty() -> None:
    vertices = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0]])  # +Z: behind an identity camera
    rgb, mask = render_mesh(vertices, np.array([[0, 1, 2]]), np.eye(4), (20.0, 20.0, 10.0, 10.0), (20, 20), colors=np.ones((3, 3)))
    assert not mask.any() and np.all(rgb == 1.0)
    face_id, _, _ = rasterize(np.zeros((0, 2)), None, np.zeros((0, 3), int), (4, 4))
    assert (face_id == -1).all()
    with pytest.raises(ValueError, match="either colors"):
        render_mesh(vertices, np.array([[0, 1, 2]]), np.eye(4), (20.0, 20.0, 10.0, 10.0), (20, 20))


@pytest.mark.parametrize("perspective", [True, False])
def test_the_c_rasterizer_draws_what_the_numpy_one_does(perspective: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """raster.c against the numpy code it replaces: a few hundred overlapping triangles of random depths (shared
    edges, faces partly off the image, degenerate ones), the same face, weights and depth at every pixel."""
    from recon.geometry import raster

    if raster.native_rasterizer() is None:
        pytest.skip("no C compiler here: the numpy rasterizer is the only one")
    rng = np.random.default_rng(5)
    xy = rng.uniform(-10.0, 74.0, (300, 2))
    w = rng.uniform(0.5, 3.0, 300) if perspective else None
    faces = np.concatenate([rng.integers(0, 300, (400, 3)), [[0, 1, 2], [2, 1, 3], [4, 4, 5]]])  # a shared edge, a degenerate face
    xy[7], xy[8, 0] = np.nan, np.inf  # faces with a non-finite corner are not drawn
    if w is not None:
        w[9], w[10], w[11] = -1.0, 0.0, np.nan  # behind, at and undefined: dropped
    native = rasterize(xy, w, faces, (48, 64))
    monkeypatch.setattr(raster, "native_rasterizer", lambda: None)
    reference = rasterize(xy, w, faces, (48, 64))
    assert (native[0] >= 0).mean() > 0.5  # most pixels covered: the comparison is not of empty images
    np.testing.assert_array_equal(native[0], reference[0])
    np.testing.assert_allclose(native[1], reference[1], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(native[2], reference[2])
    drawn = np.unique(native[0][native[0] >= 0])
    assert not np.isin(drawn, np.flatnonzero(np.isin(faces, [7, 8] + ([9, 10, 11] if perspective else [])).any(1))).any()
    with pytest.raises(IndexError):
        rasterize(xy, w, np.array([[0, 1, 300]]), (48, 64))
