"""Vertex colors from a field and from photos of a ray-traced textured sphere (closed-form ground truth)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from recon.camera import look_at as camera_look_at
from recon.camera import project
from recon.geometry.color import colors_from_field, colors_from_photos, sample_bilinear

RADIUS, W, H, F = 0.5, 192, 160, 180.0
INTR = np.array([F, F, W / 2, H / 2])


def texture(p: np.ndarray) -> np.ndarray:
    """Smooth color on the sphere, (N, 3) → (N, 3) in [0.1, 0.9]."""
    return 0.5 + 0.4 * np.sin(4.0 * p + np.array([0.0, 1.0, 2.0]))


def look_at(eye: np.ndarray) -> np.ndarray:
    """OpenGL c2w of a camera at eye looking at the origin."""
    return camera_look_at(eye, np.zeros(3))


def render(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-trace the textured sphere: image (H, W, 3), ray-distance depth (H, W), z-depth (H, W)."""
    j, i = np.mgrid[0:H, 0:W] + 0.5
    d_cam = np.stack([(i - INTR[2]) / F, -(j - INTR[3]) / F, -np.ones_like(i)], axis=-1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = c2w[:3, 3]
    b = d @ o
    disc = b**2 - (o @ o - RADIUS**2)
    hit = disc > 0
    t = np.where(hit, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    image = np.zeros((H * W, 3))
    image[hit] = texture(o + t[hit, None] * d[hit])
    z = t * (d @ -c2w[:3, 2])
    return image.reshape(H, W, 3), t.reshape(H, W), z.reshape(H, W)


@pytest.fixture(scope="module")
def ball():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    return mesh.vertices, mesh.vertices / RADIUS


@pytest.fixture(scope="module")
def views():
    eyes = 2.5 * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    eyes = eyes + np.array([0.1, 0.2, 0.3])  # off-axis, so no vertex sits on a symmetric tie
    c2ws = np.stack([look_at(e) for e in eyes])
    renders = [render(c) for c in c2ws]
    return c2ws, [r[0] for r in renders], [r[1] for r in renders], [r[2] for r in renders]


def test_project_closed_form():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.0, 0.0, 3.0]  # at +Z, looking down -Z at the origin
    uv, z = project(np.array([[0.0, 0.0, 0.0], [0.3, 0.6, 0.0], [0.0, 0.0, 4.0]]), c2w, INTR)
    np.testing.assert_allclose(uv[:2], [[W / 2, H / 2], [W / 2 + F * 0.1, H / 2 - F * 0.2]])
    np.testing.assert_allclose(z, [3.0, 3.0, -1.0])  # last point is behind the camera


def test_sample_bilinear_hits_pixel_centres_and_interpolates():
    img = np.arange(12, dtype=np.float64).reshape(3, 4, 1)
    out = sample_bilinear(img, np.array([[0.5, 0.5], [2.5, 1.5], [1.0, 0.5], [100.0, 100.0]]))
    np.testing.assert_allclose(out[:, 0], [0.0, 6.0, 0.5, 11.0])


def test_photos_reproduce_texture(ball, views):
    verts, normals = ball
    c2ws, images, depths, _ = views
    colors, seen = colors_from_photos(verts, normals, images, c2ws, np.tile(INTR, (6, 1)), depths)
    assert seen.all() and colors.shape == verts.shape and colors.dtype == np.float32
    err = np.abs(colors - texture(verts))
    assert err.mean() < 1e-3 and err.max() < 0.01  # measured 7.5e-5 and 1.1e-3


def test_depth_test_rejects_an_occluder(ball, views):
    """View 0 is blocked by a red wall in front of the ball: only the depth test keeps it out."""
    verts, normals = ball
    c2ws, images, depths, _ = views
    blocked_img, blocked_depth = list(images), list(depths)
    blocked_img[0] = np.broadcast_to([1.0, 0.0, 0.0], (H, W, 3))
    blocked_depth[0] = np.full((H, W), 1.0)  # wall 1 unit from the camera, the ball is ~2 units away
    intr = np.tile(INTR, (6, 1))
    truth = texture(verts)
    good, _ = colors_from_photos(verts, normals, blocked_img, c2ws, intr, blocked_depth)
    fooled, _ = colors_from_photos(verts, normals, blocked_img, c2ws, intr, None, reduce="mean")
    facing0 = normals @ (c2ws[0, :3, 3] / np.linalg.norm(c2ws[0, :3, 3])) > 0.5
    assert np.abs(good - truth)[facing0].mean() < 0.015
    assert np.abs(fooled - truth)[facing0].mean() > 0.1


def test_z_depth_maps_give_the_same_colors(ball, views):
    verts, normals = ball
    c2ws, images, ray_depths, z_depths = views
    intr = np.tile(INTR, (6, 1))
    a, _ = colors_from_photos(verts, normals, images, c2ws, intr, ray_depths, depth_kind="ray")
    b, _ = colors_from_photos(verts, normals, images, c2ws, intr, z_depths, depth_kind="z")
    wrong, _ = colors_from_photos(verts, normals, images, c2ws, intr, z_depths, depth_kind="ray", depth_tol=1e-3)
    np.testing.assert_allclose(a, b, atol=1e-3)  # a vertex right at the tolerance may flip
    assert np.abs(wrong - a).max() > 0.05  # z-depth read as ray distance fails off-axis, as it should


def test_unseen_vertices_fall_back(ball, views):
    verts, normals = ball
    c2ws, images, depths, _ = views
    one = [4]  # the camera above: the lower half of the ball is unseen
    fallback = np.tile([0.0, 1.0, 0.0], (len(verts), 1))
    colors, seen = colors_from_photos(
        verts, normals, [images[4]], c2ws[one], INTR[None], [depths[4]], fallback=fallback, chunk=100
    )
    assert 0.3 < seen.mean() < 0.6 and not seen[np.argmin(verts[:, 2])]
    np.testing.assert_array_equal(colors[~seen], fallback[~seen])
    nearest, seen2 = colors_from_photos(verts, normals, [images[4] * 255], c2ws[one], INTR[None], [depths[4]])
    np.testing.assert_array_equal(seen, seen2)
    assert np.all(np.isin(nearest[~seen].view("V12"), nearest[seen].view("V12")))  # copied from seen ones


def test_uint8_images_are_rescaled(ball, views):
    verts, normals = ball
    c2ws, images, depths, _ = views
    intr = np.tile(INTR, (6, 1))
    as_bytes = [np.round(im * 255).astype(np.uint8) for im in images]
    a, _ = colors_from_photos(verts, normals, images, c2ws, intr, depths)
    b, _ = colors_from_photos(verts, normals, as_bytes, c2ws, intr, depths)
    assert np.abs(a - b).max() < 1 / 255 + 1e-6


def test_field_colors_look_along_inward_normal(ball):
    verts, normals = ball
    calls = []

    def radiance(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        calls.append(len(x))
        return 0.5 + 0.5 * d  # reveals the direction it was asked from

    colors = colors_from_field(radiance, verts, normals * 3.0, chunk=100)  # un-normalized normals are fine
    np.testing.assert_allclose(colors, 0.5 - 0.5 * normals, atol=1e-6)
    assert max(calls) == 100 and sum(calls) == len(verts)


def test_the_weighted_median_is_the_value_where_half_the_weight_is_reached() -> None:
    """Against a plain per-point, per-channel reference: the smallest sample whose cumulative weight (samples in
    ascending order) reaches half the point's total; unseen views (weight 0) and tied values among them."""
    from recon.geometry.color import _weighted_median

    rng = np.random.default_rng(3)
    k, n = 9, 200
    values = np.round(rng.random((k, n, 3)), 1).astype(np.float32)  # rounded: many ties
    weights = (rng.random((k, n)) * (rng.random((k, n)) < 0.5)).astype(np.float32)
    weights[0] += 0.01  # every point seen at least once
    expected = np.empty((n, 3), np.float32)
    for i in range(n):
        for c in range(3):
            pairs = sorted(zip(values[:, i, c], weights[:, i]))
            half, acc = 0.5 * sum(w for _, w in pairs), 0.0
            for v, w in pairs:
                acc += w
                if acc >= half:
                    expected[i, c] = v
                    break
    np.testing.assert_array_equal(_weighted_median(values, weights), expected)


@pytest.mark.parametrize("case", ["ray-depths-median", "z-depths-uint8-occluded", "no-depths-mean"])
def test_the_torch_bake_equals_the_numpy_reference(ball, views, device, case):
    """`colors_from_photos` with a device (the mesh stage's CUDA path) against the numpy loop, on each device: the
    same seen flags and colours, an occluder in view 0 and points the views do not see included."""
    verts, normals = ball
    c2ws, images, ray_depths, z_depths = views
    intr = np.tile(INTR, (6, 1))
    images, kind, depths, reduce = list(images), "ray", list(ray_depths), "median"
    if case == "z-depths-uint8-occluded":
        images = [np.round(im * 255).astype(np.uint8) for im in images]
        images[0] = np.broadcast_to(np.array([255, 0, 0], np.uint8), (H, W, 3))
        kind, depths = "z", [np.full((H, W), 1.0, np.float32), *[d.astype(np.float32) for d in z_depths[1:]]]
    elif case == "no-depths-mean":
        depths, reduce = None, "mean"
    verts = np.concatenate([verts, [[5.0, 5.0, 5.0]]])  # behind or outside every view's image
    normals = np.concatenate([normals, [[0.0, 0.0, 1.0]]])
    want = colors_from_photos(verts, normals, images[:4], c2ws[:4], intr[:4], None if depths is None else depths[:4],
                              depth_kind=kind, reduce=reduce, fallback=np.zeros_like(verts))
    got = colors_from_photos(verts, normals, images[:4], c2ws[:4], intr[:4], None if depths is None else depths[:4],
                             depth_kind=kind, reduce=reduce, fallback=np.zeros_like(verts), device=device)
    np.testing.assert_array_equal(got[1], want[1])
    assert 0 < want[1].sum() < len(verts)
    np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-6)


@pytest.mark.parametrize("kind", ["ray", "z"])
def test_the_torch_view_count_equals_the_numpy_reference(ball, views, device, kind):
    """`seen_by_views` with a device (the mesh stage's CUDA path) against the numpy loop, on each device: the same
    count for every vertex, with a view whose depth map holds an occluder in front of part of the ball (those
    vertices fail its depth test), a point behind every camera, and the 3×3 window at the map's edge."""
    verts, normals = ball
    c2ws, _, ray_depths, z_depths = views
    maps = [np.asarray(d, np.float32) for d in (ray_depths if kind == "ray" else z_depths)]
    maps[0] = maps[0].copy()
    maps[0][: H // 2] = np.minimum(maps[0][: H // 2], 1.0)  # an occluder over the top half of view 0
    maps[1] = maps[1].copy()
    maps[1][:, 0] = 0.5  # an edge column: the window there reads only the image's own pixels
    verts = np.concatenate([verts, [[5.0, 5.0, 5.0]]])
    normals = np.concatenate([normals, [[0.0, 0.0, 1.0]]])
    intr = np.tile(INTR, (len(maps), 1))
    from recon.geometry.color import seen_by_views

    want = seen_by_views(verts, normals, maps, c2ws, intr, 0.02, depth_kind=kind)
    got = seen_by_views(verts, normals, maps, c2ws, intr, 0.02, depth_kind=kind, device=device)
    np.testing.assert_array_equal(got, want)
    unoccluded = seen_by_views(verts, normals, [np.asarray(d, np.float32) for d in (ray_depths if kind == "ray" else z_depths)],
                               c2ws, intr, 0.02, depth_kind=kind)
    assert (want <= unoccluded).all() and (want < unoccluded).sum() > 10  # the occluder hid some vertices from view 0
    assert want.max() >= 2 and want[-1] == 0
