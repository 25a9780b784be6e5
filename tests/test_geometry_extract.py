"""Density grid sampling, coarse-to-fine sampling, iso-level choice and marching cubes on analytic shapes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from recon.camera import image_rays, look_at
from recon.geometry.extract import (
    auto_iso_level,
    behind_views,
    close_solid,
    density_grid,
    density_grid_sparse,
    fill_enclosed,
    grid_spacing,
    marching_cubes,
)

AABB = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RADIUS, MAJOR, MINOR = 0.5, 0.55, 0.2
SIGMA = 100.0


def sphere_density(x: torch.Tensor) -> torch.Tensor:
    """Smooth solid ball: σ = SIGMA inside radius RADIUS, 0 outside, σ = SIGMA/2 exactly on the sphere."""
    assert x.dtype == torch.float32 and x.ndim == 2 and x.shape[1] == 3
    return SIGMA * torch.sigmoid((RADIUS - x.norm(dim=-1)) * 60.0)


def torus_signed(x: np.ndarray | torch.Tensor):
    """Signed distance to the torus around +Z (major MAJOR, minor MINOR); negative inside."""
    lib = torch if isinstance(x, torch.Tensor) else np
    ring = lib.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2) - MAJOR
    return lib.sqrt(ring**2 + x[:, 2] ** 2) - MINOR


def torus_density(x: torch.Tensor) -> torch.Tensor:
    return SIGMA * torch.sigmoid(-torus_signed(x) * 60.0)


def test_density_grid_matches_direct_evaluation_on_anisotropic_grid():
    aabb = np.array([[-1.0, -0.5, 0.0], [1.0, 0.5, 3.0]])
    res = (5, 7, 4)
    fn = lambda x: x[:, 0] + 10 * x[:, 1] + 100 * x[:, 2]  # noqa: E731 - linear, so node positions are exact
    grid = density_grid(fn, aabb, res, chunk=11)  # chunk that divides nothing
    axes = [np.linspace(aabb[0, d], aabb[1, d], res[d]) for d in range(3)]
    xs, ys, zs = np.meshgrid(*axes, indexing="ij")
    assert grid.shape == res and grid.dtype == np.float32
    np.testing.assert_allclose(grid, xs + 10 * ys + 100 * zs, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(grid_spacing(aabb, res), [0.5, 1 / 6, 1.0])


def test_density_grid_accepts_column_output_and_torch_aabb():
    grid = density_grid(lambda x: x[:, :1] * 0 + 3.0, torch.tensor(AABB, dtype=torch.float32), 4)
    assert np.all(grid == 3.0)


def test_marching_cubes_sphere_is_close_outward_and_watertight():
    res = 64
    grid = density_grid(sphere_density, AABB, res)
    verts, faces = marching_cubes(grid, SIGMA / 2, AABB)
    cell = 2.0 / (res - 1)
    radii = np.linalg.norm(verts, axis=1)
    assert np.abs(radii - RADIUS).max() < 0.05 * cell  # linear interpolation on a smooth density
    mesh = trimesh.Trimesh(verts, faces)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.01)  # signed: > 0 means outward
    centroids = mesh.triangles_center
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, centroids) > 0)


def test_marching_cubes_torus_has_genus_one_and_lies_on_surface():
    res = 72
    grid = density_grid(torus_density, AABB, res)
    verts, faces = marching_cubes(grid, SIGMA / 2, AABB)
    mesh = trimesh.Trimesh(verts, faces)
    assert mesh.is_watertight and mesh.euler_number == 0  # V - E + F = 0 for a torus
    assert np.abs(torus_signed(verts.astype(np.float64))).max() < 0.1 * 2.0 / (res - 1)
    assert mesh.volume == pytest.approx(2 * math.pi**2 * MAJOR * MINOR**2, rel=0.01)


def test_marching_cubes_rejects_level_outside_range():
    grid = np.zeros((4, 4, 4), np.float32)
    grid[1:3, 1:3, 1:3] = 1.0
    with pytest.raises(ValueError, match="outside the density range"):
        marching_cubes(grid, 2.0, AABB)


def test_sparse_grid_meshes_exactly_like_dense_and_saves_work():
    both = lambda x: torch.maximum(sphere_density(x - 0.35), torus_density(x + 0.2))  # noqa: E731
    res, iso = 97, SIGMA / 2
    dense = density_grid(both, AABB, res)
    sparse, info = density_grid_sparse(both, AABB, res, iso=iso, coarse=25, dilate=1)
    assert info["dense"] == res**3 and info["evaluated"] < 0.5 * res**3
    assert info["active_blocks"] < info["blocks"]
    # Inactive nodes hold interpolated values, but always on the same side of iso as the truth.
    assert np.array_equal(dense >= iso, sparse >= iso)
    vd, fd = marching_cubes(dense, iso, AABB)
    vs, fs = marching_cubes(sparse, iso, AABB)
    assert len(fd) == len(fs)
    np.testing.assert_allclose(np.sort(vd, axis=0), np.sort(vs, axis=0), atol=1e-6)


def test_sparse_grid_with_no_surface_is_all_upsampled():
    sparse, info = density_grid_sparse(lambda x: x[:, 0] * 0 + 1.0, AABB, 33, iso=5.0, coarse=5)
    # 5³ coarse nodes plus the grid's last node layer on each axis (33³ - 32³ nodes), nothing else.
    assert info["active_blocks"] == 0 and info["evaluated"] == 125 + 33**3 - 32**3
    assert np.all(sparse == 1.0)


def test_auto_iso_level_rule_clamp_override_and_fallback():
    grid = np.linspace(0, 1000, 4**3, dtype=np.float32).reshape(4, 4, 4)
    level, why = auto_iso_level(grid, cell_size=0.01)
    assert level == pytest.approx(math.log(2) / 0.01) and "50% opaque" in why
    level, why = auto_iso_level(grid, cell_size=1e-6, clamp=(1.0, 500.0))
    assert level == 500.0 and "clamped" in why
    level, why = auto_iso_level(grid, cell_size=0.01, override=12.5)
    assert level == 12.5 and "caller" in why
    level, why = auto_iso_level(grid * 1e-3, cell_size=0.01)  # max density 1 < ln2/0.01: use mid-range
    assert level == pytest.approx(0.5) and "mid-range" in why
    with pytest.raises(ValueError, match="constant"):
        auto_iso_level(np.ones((3, 3, 3), np.float32), 0.01)


def test_nan_nodes_are_tolerated_as_empty_space():
    grid = density_grid(sphere_density, AABB, 33)
    clean_faces = len(marching_cubes(grid, SIGMA / 2, AABB)[1])
    grid[0, 0, 0] = np.nan  # a corner far from the surface
    level, _ = auto_iso_level(grid, cell_size=2 / 32, clamp=(SIGMA / 2, SIGMA / 2))
    assert level == SIGMA / 2
    assert len(marching_cubes(grid, level, AABB)[1]) == clean_faces


def _shell_grid(n: int = 64, inner: float = 0.5, outer: float = 0.6, hole: float = 0.0, opening: float = 0.0) -> np.ndarray:
    """σ on an n³ grid over AABB: a spherical shell (SIGMA between the radii), with a square hole of half-width
    ``hole`` through its top, or the whole cap above z = ``opening`` cut off (a bowl) when that is < outer."""
    lin = np.linspace(-1.0, 1.0, n)
    x, y, z = np.meshgrid(lin, lin, lin, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    grid = np.where((r > inner) & (r < outer), SIGMA, 0.0).astype(np.float32)
    if hole:
        grid[(np.abs(x) < hole) & (np.abs(y) < hole) & (z > 0)] = 0.0
    if opening:
        grid[z > opening] = 0.0
    return grid


def _inner_wall_vertices(grid: np.ndarray, inner: float = 0.5) -> int:
    vertices, _ = marching_cubes(grid, SIGMA / 2, AABB)
    r = np.linalg.norm(vertices, axis=1)
    return int((r < inner + 0.5 * float(grid_spacing(AABB, grid.shape).max())).sum())


def test_fill_enclosed_fills_a_hollow_behind_a_narrow_hole_and_its_inner_wall_goes() -> None:
    cell = 2.0 / 63
    grid = _shell_grid(hole=1.2 * cell)  # a hole 2.4 cells wide through the shell's top
    assert _inner_wall_vertices(grid) > 1000  # marching cubes meshes the inner wall of the hollow
    unfilled, info0 = fill_enclosed(grid.copy(), SIGMA / 2, 0)
    assert info0["filled_nodes"] == 0  # without a ball the hole connects the hollow to the outside
    filled, info = fill_enclosed(grid.copy(), SIGMA / 2, 2)
    lin = np.linspace(-1.0, 1.0, 64)
    inside = np.sqrt(sum(c * c for c in np.meshgrid(lin, lin, lin, indexing="ij"))) < 0.5 - 2 * cell
    assert info["filled_nodes"] >= inside.sum() * 0.95 and (filled[inside] > SIGMA / 2).mean() > 0.99
    assert _inner_wall_vertices(filled) == 0
    assert (filled[grid > SIGMA / 2] == SIGMA).all()  # material is left as it was


def test_fill_enclosed_keeps_a_bowl_and_a_hole_wider_than_the_ball_open() -> None:
    bowl = _shell_grid(opening=0.2)  # the cap above z = 0.2 is gone: an opening 0.9 wide, ~28 cells
    out, info = fill_enclosed(bowl.copy(), SIGMA / 2, 3)
    assert info["filled_nodes"] == 0 and np.array_equal(out, bowl)
    wide = _shell_grid(hole=0.2)  # a hole 13 cells wide: a ball of 3 cells passes it
    _, info = fill_enclosed(wide.copy(), SIGMA / 2, 3)
    assert info["filled_nodes"] == 0


def test_fill_enclosed_fills_a_sealed_void_without_a_ball() -> None:
    sealed = _shell_grid()
    out, info = fill_enclosed(sealed.copy(), SIGMA / 2, 0)
    assert info["filled_nodes"] > 0 and _inner_wall_vertices(out) == 0


def _node_radius(n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    lin = np.linspace(-1.0, 1.0, n)
    x, y, z = np.meshgrid(lin, lin, lin, indexing="ij")
    return np.sqrt(x * x + y * y + z * z), z


def test_a_closed_solid_is_filled_where_its_shell_is_open_capped_on_its_support_and_closed_at_the_box() -> None:
    grid = _shell_grid(hole=0.2)  # a hole 13 cells wide: the hollow fill cannot close it
    r, z = _node_radius()
    plane = np.array([0.0, 0.0, 1.0, -0.3])  # the support: everything below z = -0.3 goes
    hidden = r < 0.45  # what no photo sees empty: the inside
    cell = 2.0 / 63
    solid = ((r < 0.6) & (z >= -0.3)).sum() * cell**3  # the ball above the support, to a cell

    closed, info = close_solid(grid.copy(), SIGMA / 2, AABB, plane, 3, hidden)
    mesh = trimesh.Trimesh(*marching_cubes(closed, SIGMA / 2, AABB))
    assert mesh.is_watertight and mesh.vertices[:, 2].min() > -0.3 - cell
    assert abs(mesh.volume / solid - 1) < 0.05 and info["hidden_nodes"] > 0
    cap = np.abs(mesh.vertices[:, 2] + 0.3) < 0.5 * cell
    assert cap.sum() > 100  # a flat base where the support was

    hollow, _ = close_solid(grid.copy(), SIGMA / 2, AABB, plane, 3)  # the same without the views' inside
    shell = trimesh.Trimesh(*marching_cubes(hollow, SIGMA / 2, AABB))
    assert shell.is_watertight and shell.volume < 0.6 * mesh.volume  # closed, but only around the shell

    touching = _shell_grid(outer=1.2)  # material out to the box: closed there too
    boxed, _ = close_solid(touching, SIGMA / 2, AABB, None, 0)
    assert trimesh.Trimesh(*marching_cubes(boxed, SIGMA / 2, AABB)).is_watertight


def test_close_solid_empties_the_material_keep_rejects_before_filling() -> None:
    grid = _shell_grid()
    grid[(np.abs(_node_radius()[0] - 0.8) < 0.05)] = SIGMA  # a second shell around the first, as a halo
    closed, info = close_solid(grid.copy(), SIGMA / 2, AABB, None, 0, keep=lambda p: np.linalg.norm(p, axis=1) < 0.7)
    mesh = trimesh.Trimesh(*marching_cubes(closed, SIGMA / 2, AABB))
    assert info["dropped_nodes"] > 0 and np.linalg.norm(mesh.vertices, axis=1).max() < 0.7
    assert mesh.is_watertight and abs(mesh.volume / (4 / 3 * math.pi * 0.6**3) - 1) < 0.05


def _sphere_depths(radius: float, eyes: list[np.ndarray], size: int = 48, focal: float = 60.0):
    """Each camera's ray distance to a ball of ``radius`` at the origin (inf where its rays miss it)."""
    k = np.array([focal, focal, size / 2, size / 2])
    c2ws, depths = [], []
    for eye in eyes:
        c2w = look_at(np.asarray(eye, np.float64), np.zeros(3), (0.0, 0.0, 1.0) if abs(eye[2]) < 2 else (0.0, 1.0, 0.0))
        o, d = image_rays(c2w, *k, size, size)
        b = np.einsum("hwc,hwc->hw", o, d)
        disc = b * b - (np.einsum("hwc,hwc->hw", o, o) - radius**2)
        depths.append(np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf))
        c2ws.append(c2w)
    return depths, np.stack(c2ws), np.tile(k, (len(eyes), 1))


def test_behind_views_finds_the_inside_of_what_the_views_show_and_nothing_outside() -> None:
    eyes = [np.array(e, np.float64) * 3 for e in
            [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1), (1, 1, 1), (-1, -1, 1)]]
    depths, c2ws, intr = _sphere_depths(0.5, eyes)
    hidden = behind_views(AABB, (64, 64, 64), depths, c2ws, intr, tol=0.02)
    r, _ = _node_radius()
    assert not hidden[r > 0.5].any()  # nothing a view sees empty
    assert hidden[r < 0.3].mean() > 0.95  # the inside, less a shell a coarse step thick
    one, c2w1, k1 = _sphere_depths(0.5, eyes[:1] * 2)  # a photo taken twice from one place
    seen_once = behind_views(AABB, (64, 64, 64), one, c2w1, k1, tol=0.02)
    assert seen_once[r > 0.6].sum() > 1000  # from one place the ball's whole shadow is hidden: other views carve it
    assert not behind_views(AABB, (64, 64, 64), one[:1], c2w1[:1], k1[:1], tol=0.02).any()  # one view frames too few
