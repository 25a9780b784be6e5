"""Density field → grid → triangle mesh (marching cubes), all in the normalized scene frame.

Grid convention used throughout: node ``(i, j, k)`` of an ``(Rx, Ry, Rz)`` grid sits at
``aabb[0] + (i, j, k) * (aabb[1] - aabb[0]) / (R - 1)``, i.e. the first and last nodes lie on the box
faces. Array axis 0 is scene x, axis 1 is y, axis 2 is z, so ``grid[i, j, k]`` is the density at that
point and marching cubes with ``spacing = cell size`` returns vertices directly in scene units.

Densities are volume densities σ (1 / scene unit), high inside the object.
"""
from __future__ import annotations

import math
from typing import Callable, Protocol, Sequence

import numpy as np
import torch
from scipy.ndimage import binary_dilation, binary_erosion, label, maximum_filter
from skimage import measure

from recon.camera import project


class GridSettings(Protocol):
    """What `choose_resolution` reads (recon.config.MeshConfig has these): the library needs no config import."""

    resolution: int
    max_resolution: int
    memory_budget_mb: int


DensityFn = Callable[[torch.Tensor], torch.Tensor]
"""``density_fn(points: (M, 3) float32) -> (M,)`` or ``(M, 1)`` density σ ≥ 0 at scene points."""


def _as_aabb(aabb: np.ndarray | torch.Tensor) -> np.ndarray:
    """aabb: (2, 3) min/max corners → float64 numpy, checked to be a non-empty box."""
    box = aabb.detach().cpu().double().numpy() if isinstance(aabb, torch.Tensor) else np.asarray(aabb, np.float64)
    if box.shape != (2, 3) or not np.all(box[1] > box[0]):
        raise ValueError(f"aabb must be (2, 3) [min, max] with max > min on every axis, got {box.tolist()}")
    return box


def _as_resolution(resolution: int | tuple[int, int, int]) -> tuple[int, int, int]:
    res = (resolution,) * 3 if isinstance(resolution, (int, np.integer)) else tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 2:
        raise ValueError(f"resolution must be an int or 3 ints, each >= 2 (nodes per axis), got {resolution}")
    return res  # type: ignore[return-value]


def grid_spacing(aabb: np.ndarray | torch.Tensor, resolution: int | tuple[int, int, int]) -> np.ndarray:
    """Distance between neighbouring grid nodes per axis, (3,) in scene units."""
    box = _as_aabb(aabb)
    return (box[1] - box[0]) / (np.asarray(_as_resolution(resolution), np.float64) - 1)


def surface_cell(aabb: np.ndarray | torch.Tensor, shape: tuple[int, int, int], voxel: float) -> tuple[float, str]:
    """The finest layer thickness the mesh can trust (scene units) and why: the mesh grid's cell, or the
    field's own voxel (``voxel``: `voxel_size` of grid models, 0 for others) when that is coarser — a field cannot
    make material thinner than its voxel opaque, so an iso-level from a finer mesh cell would cut holes in its shell."""
    cell = float(grid_spacing(aabb, shape).max())
    if voxel > cell:
        return voxel, f"the field's voxel {voxel:.4g} (coarser than the mesh cell {cell:.4g})"
    return cell, f"the mesh cell {cell:.4g}"


def _device_of(aabb: np.ndarray | torch.Tensor, device: torch.device | str | None) -> torch.device:
    if device is not None:
        return torch.device(device)
    return aabb.device if isinstance(aabb, torch.Tensor) else torch.device("cpu")


def _evaluate(density_fn: DensityFn, points: torch.Tensor) -> np.ndarray:
    """Run density_fn on (M, 3) points without autograd; (M,) float32 numpy."""
    with torch.no_grad():
        sigma = density_fn(points)
    sigma = sigma.reshape(points.shape[0], -1)
    if sigma.shape[1] != 1:
        raise ValueError(f"density_fn must return (M,) or (M, 1) densities, got {tuple(sigma.shape)}")
    return sigma[:, 0].float().cpu().numpy()


def _evaluate_indices(
    density_fn: DensityFn, ijk: np.ndarray, lo: np.ndarray, step: np.ndarray, device: torch.device
) -> np.ndarray:
    """Densities at integer grid nodes ijk: (M, 3) → (M,) float32; coordinates built in float32 on device."""
    idx = torch.from_numpy(np.ascontiguousarray(ijk)).to(device)
    lo_t = torch.as_tensor(lo, dtype=torch.float32, device=device)
    step_t = torch.as_tensor(step, dtype=torch.float32, device=device)
    return _evaluate(density_fn, lo_t + idx.float() * step_t)


def density_grid(
    density_fn: DensityFn,
    aabb: np.ndarray | torch.Tensor,
    resolution: int | tuple[int, int, int],
    chunk: int = 2**18,
    device: torch.device | str | None = None,
) -> np.ndarray:
    """Sample σ on every node of a regular grid spanning aabb; returns (Rx, Ry, Rz) float32.

    Memory stays bounded by ``chunk``: each chunk's node coordinates are generated from flat indices
    (no full meshgrid), evaluated under ``torch.no_grad`` on ``device`` (default: aabb's device, else
    CPU) and written into the preallocated output (4·R³ bytes, 512 MiB at R = 512).

    Example: ``density_grid(lambda x: (x.norm(dim=-1) < 0.5).float() * 100, [[-1]*3, [1]*3], 64)``.
    """
    box, res = _as_aabb(aabb), _as_resolution(resolution)
    dev, step = _device_of(aabb, device), grid_spacing(box, res)
    out = np.empty(res, np.float32)
    flat = out.reshape(-1)
    n, yz = flat.size, res[1] * res[2]
    for start in range(0, n, chunk):
        idx = np.arange(start, min(start + chunk, n), dtype=np.int64)
        ijk = np.stack([idx // yz, (idx // res[2]) % res[1], idx % res[2]], axis=-1)
        flat[start : start + idx.size] = _evaluate_indices(density_fn, ijk, box[0], step, dev)
    return out


def _coarse_nodes(r: int, coarse: int) -> np.ndarray:
    """Fine-grid indices of the coarse nodes along one axis: every s-th node plus the last one."""
    s = max(1, (r - 1) // max(coarse - 1, 1))
    return np.unique(np.r_[np.arange(0, r - 1, s), r - 1])


def _interp_matrix(nodes: np.ndarray, r: int) -> np.ndarray:
    """(r, C) float32 matrix of 1-D linear interpolation from coarse nodes (fine indices) to 0..r-1."""
    f = np.arange(r)
    a = np.clip(np.searchsorted(nodes, f, side="right") - 1, 0, len(nodes) - 2)
    w = ((f - nodes[a]) / (nodes[a + 1] - nodes[a])).astype(np.float32)
    mat = np.zeros((r, len(nodes)), np.float32)
    mat[f, a], mat[f, a + 1] = 1 - w, w
    return mat


def _upsample_into(out: np.ndarray, coarse_vals: np.ndarray, nodes: tuple[np.ndarray, ...]) -> None:
    """Trilinear upsampling of coarse node values (Cx, Cy, Cz) into out (Rx, Ry, Rz), separably.

    z and y are interpolated by two small matrix products into (Cx, Ry, Rz) (68 MB at R = 512, coarse
    65); each x slab of out is then a blend of two of those planes, written in place.
    """
    wx, wy, wz = (_interp_matrix(n, r) for n, r in zip(nodes, out.shape))
    planes = np.matmul(wy, coarse_vals.astype(np.float32) @ wz.T)  # (Cx, Ry, Rz)
    for i, row in enumerate(wx):
        a, b = np.flatnonzero(row)[[0, -1]]
        np.multiply(planes[a], row[a], out=out[i])
        if b != a:
            out[i] += planes[b] * row[b]


def density_grid_sparse(
    density_fn: DensityFn,
    aabb: np.ndarray | torch.Tensor,
    resolution: int | tuple[int, int, int],
    iso: float,
    coarse: int = 64,
    dilate: int = 1,
    chunk: int = 2**18,
    device: torch.device | str | None = None,
) -> tuple[np.ndarray, dict]:
    """Coarse-to-fine σ grid: full resolution only in blocks that the iso-surface crosses.

    1. Evaluate σ on a coarse grid (``coarse`` nodes per axis) whose nodes are a subset of the fine
       nodes (every s-th, s = (R-1) // (coarse-1), plus the last), so coarse values are exact.
    2. A block (the fine cells between neighbouring coarse nodes) is *active* when its 8 corner values
       straddle ``iso`` (min < iso ≤ max); active blocks are dilated by ``dilate`` blocks to catch
       surface that bulges past a block's corners.
    3. Every node gets the trilinear upsampling of the coarse grid; all nodes of active blocks (faces
       included) are then overwritten with real evaluations, each node evaluated once. Trilinear values
       are convex combinations of a block's corners, so an inactive block stays strictly on one side of
       ``iso`` and marching cubes puts no triangle there: the mesh equals the dense grid's mesh wherever
       the coarse pass detected the surface (exactly, in the tests).

    Limitation: a feature thinner than one coarse block that falls between its corners (and its
    dilation) is missed; raise ``coarse`` for thin structures. Memory is not saved: the output is the
    dense (R, R, R) float32 array (512 MiB at R = 512) that marching cubes needs.

    The mesh is the same as the dense evaluation's, from a fraction of the density calls (a sphere and torus
    filling ~40 % of the box at R = 512: about a sixth of the nodes); the saving grows with R (surface ∝ R²,
    volume ∝ R³), so it matters most when the density is an MLP.

    Returns ``(grid (Rx, Ry, Rz) float32, info)``; info: ``evaluated`` (points passed to density_fn),
    ``dense`` (R³), ``active_blocks`` (blocks evaluated at full resolution), ``blocks``, ``block`` (s).
    """
    box, res = _as_aabb(aabb), _as_resolution(resolution)
    dev, step = _device_of(aabb, device), grid_spacing(box, res)
    nodes = tuple(_coarse_nodes(r, coarse) for r in res)
    cijk = np.stack(np.meshgrid(*nodes, indexing="ij"), axis=-1).reshape(-1, 3)
    cvals = np.concatenate(
        [_evaluate_indices(density_fn, cijk[i : i + chunk], box[0], step, dev) for i in range(0, len(cijk), chunk)]
    ).reshape(tuple(len(n) for n in nodes))

    corners = [cvals[a : a + cvals.shape[0] - 1, b : b + cvals.shape[1] - 1, c : c + cvals.shape[2] - 1]
               for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    lo, hi = np.minimum.reduce(corners), np.maximum.reduce(corners)
    active = (lo < iso) & (hi >= iso)
    if dilate > 0 and active.any():
        active = binary_dilation(active, structure=np.ones((3, 3, 3), bool), iterations=dilate)
    # Each block owns its nodes half-open, [start, end) per axis, so no node is evaluated twice; the far
    # faces of an active block belong to its +x/+y/+z neighbours, which are therefore evaluated too.
    owners = active.copy()
    for sx, sy, sz in np.ndindex(2, 2, 2):
        nx, ny, nz = active.shape
        owners[sx:, sy:, sz:] |= active[: nx - sx, : ny - sy, : nz - sz]

    out = np.empty(res, np.float32)
    _upsample_into(out, cvals, nodes)

    evaluated = len(cijk)

    def fill(ijk: np.ndarray) -> None:
        nonlocal evaluated
        out[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = _evaluate_indices(density_fn, ijk, box[0], step, dev)
        evaluated += len(ijk)

    blocks = np.argwhere(owners)  # (B, 3) block indices
    s = max(int(np.diff(n).max()) for n in nodes)
    offsets = np.stack(np.meshgrid(*(np.arange(s),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    starts = np.stack([nodes[d][blocks[:, d]] for d in range(3)], axis=-1)
    ends = np.stack([nodes[d][blocks[:, d] + 1] for d in range(3)], axis=-1)
    full = np.all(ends - starts == s, axis=1)
    per_chunk = max(1, chunk // len(offsets))
    for b in range(0, len(blocks), per_chunk):
        ijk = starts[b : b + per_chunk, None, :] + offsets[None]  # (b, s³, 3)
        if not full[b : b + per_chunk].all():  # blocks at the far end may be shorter than s
            ijk = ijk[np.all(ijk < ends[b : b + per_chunk, None, :], axis=-1)]
        fill(ijk.reshape(-1, 3))
    # The grid's last node layer on each axis (index R-1) is owned by no block: evaluate it densely
    # (3R² nodes, < 1 % of R³ at R = 512), split so that no node appears twice.
    rx, ry, rz = res
    faces = [np.stack(np.meshgrid([rx - 1], np.arange(ry), np.arange(rz), indexing="ij"), -1),
             np.stack(np.meshgrid(np.arange(rx - 1), [ry - 1], np.arange(rz), indexing="ij"), -1),
             np.stack(np.meshgrid(np.arange(rx - 1), np.arange(ry - 1), [rz - 1], indexing="ij"), -1)]
    face_ijk = np.concatenate([f.reshape(-1, 3) for f in faces])
    for i in range(0, len(face_ijk), chunk):
        fill(face_ijk[i : i + chunk])
    info = {
        "evaluated": int(evaluated),
        "dense": int(np.prod(res)),
        "active_blocks": int(len(blocks)),
        "blocks": int(active.size),
        "block": int(s),
    }
    return out, info


def auto_iso_level(
    grid: np.ndarray,
    cell_size: float,
    opacity: float = 0.5,
    clamp: tuple[float, float] = (1.0, 1e4),
    override: float | None = None,
) -> tuple[float, str]:
    """Pick the σ iso-level for marching cubes and say why.

    Rule: the surface is where one grid cell of material becomes ``opacity`` opaque, i.e.
    ``1 - exp(-σ · cell_size) = opacity`` → ``σ = -ln(1 - opacity) / cell_size`` (ln 2 / cell for 0.5),
    in 1 / scene unit. This ties the level to the resolution the mesh can show: thinner, fainter
    material than one opaque-ish cell is not surface at this resolution. The value is clamped to
    ``clamp`` (1/scene unit) and then into the grid's value range so marching cubes always finds a
    surface when there is any contrast. ``override`` (the caller's level) is returned unchanged.

    grid: (Rx, Ry, Rz) densities; cell_size: scene units (largest grid spacing).
    """
    finite = grid if np.isfinite([grid.min(), grid.max()]).all() else grid[np.isfinite(grid)]  # copy only if needed
    if finite.size == 0:
        raise ValueError("density grid has no finite value; the field is broken (NaN/inf everywhere)")
    gmin, gmax = float(finite.min()), float(finite.max())
    if override is not None:
        frac = np.count_nonzero(finite > override) / finite.size
        return float(override), f"iso {override:.4g} set by caller ({frac:.2%} of nodes above)"
    if not 0 < opacity < 1 or cell_size <= 0:
        raise ValueError(f"need 0 < opacity < 1 and cell_size > 0, got {opacity}, {cell_size}")
    rule = -math.log1p(-opacity) / cell_size
    level = min(max(rule, clamp[0]), clamp[1])
    why = f"σ = -ln(1-{opacity:g}) / cell {cell_size:.4g} = {rule:.4g}: one cell of it is {opacity:.0%} opaque"
    if level != rule:
        why += f"; clamped to [{clamp[0]:g}, {clamp[1]:g}]"
    if not gmin < level < gmax:
        if gmax <= gmin:
            raise ValueError(f"density grid is constant ({gmin:g}); there is no surface to extract")
        level = gmin + 0.5 * (gmax - gmin)
        why += f"; outside the grid's range [{gmin:.4g}, {gmax:.4g}], so mid-range {level:.4g} instead"
    frac = np.count_nonzero(finite > level) / finite.size
    return float(level), f"iso {level:.4g} ({why}); {frac:.2%} of nodes above"


def marching_cubes(
    grid: np.ndarray, level: float, aabb: np.ndarray | torch.Tensor
) -> tuple[np.ndarray, np.ndarray]:
    """Iso-surface of σ = level: vertices (V, 3) float32 in scene units, faces (F, 3) int64.

    Faces are wound counter-clockwise seen from outside, so normals point out of the dense region
    (σ > level inside). Vertices keep skimage's sharing (one vertex per crossed grid edge).
    """
    box = _as_aabb(aabb)
    if grid.ndim != 3 or min(grid.shape) < 2:
        raise ValueError(f"grid must be (Rx, Ry, Rz) with every R >= 2, got {grid.shape}")
    gmin, gmax = float(grid.min()), float(grid.max())
    if not np.isfinite([gmin, gmax]).all():  # NaN (no density) → 0; copies only in this case
        grid = np.nan_to_num(grid, nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0)
        gmin, gmax = float(grid.min()), float(grid.max())
    if not gmin < level < gmax:
        raise ValueError(
            f"iso level {level:g} is outside the density range [{gmin:g}, {gmax:g}]: no surface. "
            "Lower the level or check that the field was trained (auto_iso_level picks one in range)."
        )
    spacing = tuple(grid_spacing(box, grid.shape))
    verts, faces, _, _ = measure.marching_cubes(grid, level, spacing=spacing, gradient_direction="descent")
    verts = (verts + box[0]).astype(np.float32)
    # skimage's 'descent' winding yields inward normals for σ high inside; swap two indices to face out.
    return verts, faces[:, [0, 2, 1]].astype(np.int64)


def fill_enclosed(grid: np.ndarray, level: float, hole_cells: int) -> tuple[np.ndarray, dict]:
    """Raise the empty space the material encloses above ``level``: the density field's hollow inside.

    Why: a radiance field is opaque only where the photos look, so it is a shell with a soft, empty inside, and
    marching cubes meshes the shell's inner wall too. The hidden-face test drops that wall only where no photo
    sees it; where the shell has pits and holes (a crease few photos see) the photos see the inner wall through
    them and it stays. Here the outside is the empty space a ball of radius ``hole_cells`` reaches from the grid's border
    (its centres a connected set, so it passes no hole narrower than the ball), and the empty space it does not
    reach is raised; the ball's own reach into the holes stays empty, so a hole becomes a dent as deep as the
    shell and the gaps between real parts wider than the ball are kept. Pockets smaller than (2k + 1)³ nodes are
    left: a discrete ball misses single nodes against curved walls. Returns the grid (modified in place) and what
    was filled."""
    empty = ~(grid > level)
    k = int(hole_cells)
    # ball centres: empty nodes at least k cells (6-connected steps) from material; the border counts as empty
    centres = binary_erosion(empty, iterations=k, border_value=1) if k else empty
    labels, count = label(centres)
    touches_border = np.zeros(count + 1, bool)  # per label: a lookup, not np.isin (which sorts the whole grid)
    touches_border[labels[[0, -1]].ravel()] = True
    touches_border[labels[:, [0, -1]].ravel()] = True
    touches_border[labels[:, :, [0, -1]].ravel()] = True
    touches_border[0] = False
    outside = touches_border[labels]
    del labels
    if k:
        outside = binary_dilation(outside, iterations=k, mask=empty)
    enclosed = empty & ~outside
    del outside, empty
    if k:  # pockets smaller than a cube around the ball are the ball's discretization at curved walls, not a hollow
        pockets, _ = label(enclosed)
        sizes = np.bincount(pockets.ravel())
        sizes[0] = 0
        enclosed = (sizes >= (2 * k + 1) ** 3)[pockets]
        del pockets
    n = int(enclosed.sum())
    if n:
        grid[enclosed] = np.float32(2.0 * level) if level > 0 else np.float32(level + 1.0)
    return grid, {"filled_nodes": n, "filled_fraction": n / grid.size, "hole_cells": k}


def cut_at_plane(grid: np.ndarray, level: float, aabb: np.ndarray | torch.Tensor, plane: np.ndarray,
                 slope: float) -> int:
    """Empty the grid below ``plane`` (nx, ny, nz, d; n·x = d, unit n pointing at what stays) so that marching cubes
    crosses ``level`` on the plane itself: within a cell and a half of it, and everywhere below, each node takes at
    most ``level + slope · s / cell`` (s its signed distance to the plane), a level set through the plane. A slice
    of x at a time, in place. Returns how many nodes lie below the plane."""
    box = _as_aabb(aabb)
    axes = [np.linspace(box[0, a], box[1, a], grid.shape[a]) for a in range(3)]
    n, d = np.asarray(plane[:3], np.float64), float(plane[3])
    cell = float(grid_spacing(box, grid.shape).max())
    rest = n[1] * axes[1][:, None] + n[2] * axes[2][None, :] - d
    below = 0
    for i, x in enumerate(axes[0]):
        signed = rest + n[0] * x
        near = signed < 1.5 * cell
        cap = (level + slope * signed[near] / cell).astype(grid.dtype)
        grid[i][near] = np.minimum(grid[i][near], cap)
        below += int((signed < 0).sum())
    return below


HIDDEN_NODES = 96
"""`behind_views` tests every s-th grid node, s such that this many lie along the longest axis: it only has to find
the inside, well away from the surface the density grid resolves."""
HIDDEN_FRAMED = 0.5
"""`behind_views` calls a node hidden only when at least this share of the views frame it: behind an object from the
few views that frame a node far off to its side lies space that no view could see, not the object's inside."""


def behind_views(aabb: np.ndarray | torch.Tensor, shape: tuple[int, int, int], depths: Sequence[np.ndarray],
                 c2ws: np.ndarray, intrinsics: np.ndarray, tol: float,
                 nodes: int = HIDDEN_NODES, framed_share: float = HIDDEN_FRAMED) -> np.ndarray:
    """(Rx, Ry, Rz) bool: the grid nodes that no view sees as empty space. Each view's depth map (H, W) holds the
    distance from its camera to the surface it shows (inf where it shows none); a node in its frame nearer than the
    farthest depth of the 3×3 pixels around it, less ``tol``, is seen empty. A node is behind the views when at
    least ``framed_share`` of them (and two) frame it and none sees it empty: the inside of what the photos show,
    shaped by their depths alone (space carving), so holes in the field's shell do not leave it hollow. Tested on
    every s-th node (about ``nodes`` along the longest axis), shrunk by one such step, so what it marks lies inside
    the surface."""
    box, res = _as_aabb(aabb), _as_resolution(shape)
    step = max(1, math.ceil(max(res) / nodes))
    axes = [np.linspace(box[0, a], box[1, a], res[a])[::step] for a in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    framed = np.zeros(len(points), np.int32)
    empty = np.zeros(len(points), bool)
    for depth, c2w, k in zip(depths, np.asarray(c2ws, np.float64), np.asarray(intrinsics, np.float64), strict=True):
        far = maximum_filter(np.asarray(depth, np.float64), size=3, mode="nearest")
        h, w = far.shape
        uv, z = project(points, c2w, k)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        px = uv[inside].astype(np.int64)
        dist = np.linalg.norm(points[inside] - c2w[:3, 3], axis=1)
        framed[inside] += 1
        empty[np.flatnonzero(inside)[dist < far[px[:, 1], px[:, 0]] - tol]] = True
    enough = max(2, math.ceil(framed_share * len(depths)))
    coarse = ((framed >= enough) & ~empty).reshape([len(a) for a in axes])
    coarse = binary_erosion(coarse, border_value=0)
    out = coarse
    for axis in range(3):
        out = np.repeat(out, step, axis=axis)
    return np.ascontiguousarray(out[: res[0], : res[1], : res[2]])


def close_solid(grid: np.ndarray, level: float, aabb: np.ndarray | torch.Tensor, plane: np.ndarray | None,
                hole_cells: int, hidden: np.ndarray | None = None,
                keep: Callable[[np.ndarray], np.ndarray] | None = None, chunk: int = 2**20) -> tuple[np.ndarray, dict]:
    """Make the grid's level set a closed solid: empty the material ``keep(points (N, 3)) -> (N,) bool`` rejects
    (e.g. what the photos' masks call background), raise the ``hidden`` nodes ((Rx, Ry, Rz) bool, `behind_views`:
    the inside no photo sees) and the hollow the material encloses (`fill_enclosed`, holes up to ``hole_cells``
    closed), then empty everything below the plane (nx, ny, nz, d; the ground or wall the object stands on, n
    pointing at it; None: no support) and the grid's outer node layer, so marching cubes caps the object flat on its
    support and closes it at the box.

    Why: the underside of an object on a table is never photographed, so its field is a shell open towards the table,
    often with holes where few photos agree; the space behind every photo's view of it is the object's inside (or
    what no photo can tell from it), so filling it and cutting at the table leaves a solid with a flat base. Returns
    the grid (modified in place) and what was done."""
    inside = np.float32(2.0 * level) if level > 0 else np.float32(level + 1.0)
    outside = np.float32(0.5 * level) if level > 0 else np.float32(level - 1.0)
    dropped = 0
    if keep is not None:
        box = _as_aabb(aabb)
        spacing = grid_spacing(box, grid.shape)
        material = np.flatnonzero(grid > level)
        for s in range(0, len(material), chunk):
            flat = material[s : s + chunk]
            points = box[0] + np.stack(np.unravel_index(flat, grid.shape), -1) * spacing
            gone = flat[~np.asarray(keep(points), bool)]
            grid.flat[gone] = outside
            dropped += len(gone)
        del material
    hidden_nodes = 0
    if hidden is not None:  # no photo sees it empty: inside, whatever the field's shell leaves open
        fill_in = hidden & ~(grid > level)
        hidden_nodes = int(fill_in.sum())
        grid[fill_in] = inside
        del fill_in
    grid, fill = fill_enclosed(grid, level, hole_cells)
    below = cut_at_plane(grid, level, aabb, plane, float(inside - level)) if plane is not None else 0
    for axis in range(3):
        index: list = [slice(None)] * 3
        for end in (0, -1):
            index[axis] = end
            grid[tuple(index)] = np.minimum(grid[tuple(index)], outside)
    return grid, {**fill, "dropped_nodes": dropped, "hidden_nodes": hidden_nodes, "below_plane_nodes": below}


# ---------------------------------------------------------------------------------------- resolution
def grid_shape(aabb: np.ndarray, resolution: int) -> tuple[int, int, int]:
    """Nodes per axis for cubic cells: ``resolution`` nodes along the box's longest side, the others in
    proportion (at least 2)."""
    extent = np.ptp(np.asarray(aabb, np.float64), axis=0)
    cells = (resolution - 1) * extent / extent.max()
    return tuple(max(2, int(round(c)) + 1) for c in cells)  # type: ignore[return-value]


def choose_resolution(
    aabb: np.ndarray, cfg: GridSettings, footprint: float | None, footprint_why: str = ""
) -> tuple[tuple[int, int, int], str]:
    """Grid shape (nodes per axis, cubic cells over aabb (2, 3)) and the reason for it.

    ``cfg.resolution > 0`` is used as given (nodes along the longest side); otherwise one cell per
    pixel footprint (scene units), capped by ``cfg.max_resolution``. Either way the float32 grid
    must fit in ``cfg.memory_budget_mb``; the resolution is lowered until it does.
    """
    longest = float(np.ptp(np.asarray(aabb, np.float64), axis=0).max())
    if cfg.resolution > 0:
        res, why = int(cfg.resolution), f"mesh.resolution={cfg.resolution}"
    else:
        if footprint is None or not footprint > 0:
            raise ValueError("an automatic resolution needs the pixel footprint (> 0 scene units)")
        res = int(math.ceil(longest / footprint)) + 1
        why = f"cell ≈ pixel footprint {footprint:.4g} units{footprint_why} → {res} nodes along {longest:.3g} units"
        if res > cfg.max_resolution:
            res = int(cfg.max_resolution)
            why += f", capped at mesh.max_resolution={cfg.max_resolution}"
    res = max(res, 8)
    budget = cfg.memory_budget_mb * 2**20
    shape = grid_shape(aabb, res)
    if 4 * math.prod(shape) > budget:
        before = res
        while res > 8 and 4 * math.prod(grid_shape(aabb, res)) > budget:
            factor = (budget / (4 * math.prod(grid_shape(aabb, res)))) ** (1 / 3)
            res = max(8, min(res - 1, int((res - 1) * factor) + 1))
        shape = grid_shape(aabb, res)
        why += f"; lowered from {before} to {res} to fit the float32 grid in mesh.memory_budget_mb={cfg.memory_budget_mb}"
    mb = 4 * math.prod(shape) / 2**20
    return shape, f"grid {shape[0]}×{shape[1]}×{shape[2]} ({mb:.0f} MB float32): {why}"
