"""A trained field's surface as a triangle mesh: its density (or signed distance) on a grid → level → marching cubes.

The model's side of `recon.geometry.extract`, which works on density functions and arrays: here a model
(``model.density`` or ``model.sdf``) is evaluated over a box with progress bars, and the extraction's choices
(coarse to fine or dense, the iso-level and its reason, the hollow fill) are recorded for the mesh report.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from recon.config import MeshConfig
from recon.errors import ReconError
from recon.geometry.extract import (
    auto_iso_level,
    close_solid,
    density_grid,
    density_grid_sparse,
    fill_enclosed,
    grid_spacing,
    marching_cubes,
    surface_cell,
)

COARSE_NODES = 64
"""Coarse grid nodes per axis: for coarse-to-fine refinement and for estimating the iso-level first."""
DENSITY_CHUNK = 2**16
"""Points per model.density call (the models are not chunked themselves)."""
ISO_OPACITY = 0.35
"""One cell of material this opaque is surface (`auto_iso_level`), unless mesh.iso_opacity says otherwise. A field
is soft where few photos agree (fur, foliage, a facade at a slant, an undertrained patch): at 50% its mesh falls
into pieces and holes, at 25% it grows out of the surface; 35% keeps real captures in one piece without thickening
object captures (docs/real_captures.md)."""


def field_voxel(model: torch.nn.Module) -> float:
    """The field's own voxel (scene units; `voxel_size` of grid models), 0 for a field without one."""
    return float(getattr(model, "voxel_size", 0.0) or 0.0)


def extraction_mode(coarse_to_fine: bool, shape: tuple[int, int, int]) -> tuple[str, str]:
    """"coarse-to-fine" or "dense", and why dense when coarse to fine was asked for ("" otherwise): refining
    pays only when a coarse block spans >= 2 fine cells; below that every node is coarse anyway."""
    if not coarse_to_fine:
        return "dense", ""
    if max(shape) - 1 >= 2 * (COARSE_NODES - 1):
        return "coarse-to-fine", ""
    return "dense", f"dense: the grid is too small (< {2 * COARSE_NODES - 1} nodes) for coarse-to-fine to save work"


def _counting(density_fn: Callable[[torch.Tensor], torch.Tensor], bar: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """density_fn that advances a progress bar by the number of points it evaluated."""
    def fn(x: torch.Tensor) -> torch.Tensor:
        sigma = density_fn(x)
        bar.advance(int(x.shape[0]))
        return sigma

    return fn


def extract_mesh(
    model: torch.nn.Module, aabb: torch.Tensor, shape: tuple[int, int, int], cfg: MeshConfig, report: Any,
    closed: bool = False, support: np.ndarray | None = None,
    hidden: Callable[[tuple[int, int, int]], np.ndarray] | None = None,
    keep: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Density grid over aabb (2, 3) (on aabb's device) → iso-level → marching cubes.

    ``model.density(x (M, 3)) -> (M,)`` in 1/scene unit. Coarse-to-fine (`extraction_mode`) needs the level
    before the fine grid: it is estimated with `auto_iso_level` on a 64³ preview grid (same rule, `surface_cell`)
    unless ``cfg.iso > 0`` gives it; ``cfg.iso_opacity`` 0 is ISO_OPACITY; ``cfg.fill_cavities`` fills the hollow
    (`fill_enclosed`); ``closed`` makes it a solid capped on the ``support`` plane and closed at the box
    (`close_solid`), its inside also what ``hidden(shape)`` marks (`behind_views`), its material only where
    ``keep(points)`` agrees (the masks). Returns vertices (V, 3) float32 and faces (F, 3) int64 in the scene frame,
    and info (grid, iso and its reason, counts, timings).
    """
    cell = float(grid_spacing(aabb, shape).max())
    iso_cell, iso_cell_why = surface_cell(aabb, shape, field_voxel(model))
    override = cfg.iso if cfg.iso > 0 else None
    opacity = cfg.iso_opacity or ISO_OPACITY
    mode, dense_why = extraction_mode(cfg.coarse_to_fine, shape)
    info: dict[str, Any] = {"grid": list(shape), "cell": cell, "mode": mode}
    if dense_why:
        info["mode_reason"] = dense_why
    t0 = time.perf_counter()
    dense = math.prod(shape)
    try:
        if mode == "coarse-to-fine":
            n_preview = min(COARSE_NODES, max(shape))
            with report.task("density preview grid", total=n_preview**3, unit="points") as bar:
                preview = density_grid(_counting(model.density, bar), aabb, n_preview, chunk=DENSITY_CHUNK)
            level, why = auto_iso_level(preview, iso_cell, opacity=opacity, override=override)
            if override is None:
                why += f"; cell: {iso_cell_why}; estimated on a {preview.shape[0]}³ preview grid"
            with report.task("density grid (coarse to fine)", total=None, unit="points") as bar:
                grid, sparse = density_grid_sparse(
                    _counting(model.density, bar), aabb, shape, level, coarse=COARSE_NODES, chunk=DENSITY_CHUNK
                )
            info["sparse"] = sparse
            info["evaluated"] = sparse["evaluated"] + preview.size
        else:
            with report.task("density grid", total=dense, unit="points") as bar:
                grid = density_grid(_counting(model.density, bar), aabb, shape, chunk=DENSITY_CHUNK)
            level, why = auto_iso_level(grid, iso_cell, opacity=opacity, override=override)
            if override is None:
                why += f"; cell: {iso_cell_why}"
            info["evaluated"] = dense
        info["time_grid_s"] = round(time.perf_counter() - t0, 3)
        info["iso"], info["iso_reason"] = float(level), why
        report.info(f"density grid: {info['evaluated']:,} of {dense:,} nodes evaluated in {info['time_grid_s']:.1f} s; {why}")
        if closed:
            grid, info["fill"] = close_solid(grid, level, aabb, support, cfg.fill_cavities,
                                             hidden(shape) if hidden is not None else None, keep)
            report.info("closed solid: " + (f"{info['fill']['dropped_nodes']:,} grid nodes of material the masks "
                                             "call background emptied, " if keep is not None else "")
                        + f"{info['fill']['hidden_nodes']:,} grid nodes filled that no photo sees empty, "
                        f"{info['fill']['filled_nodes']:,} more that the material encloses (holes up to "
                        f"~{2 * cfg.fill_cavities} cells closed to tell)"
                        + (", cut flat on the support" if support is not None else ""))
        elif cfg.fill_cavities:
            grid, info["fill"] = fill_enclosed(grid, level, cfg.fill_cavities)
            report.info(f"hollow filled: {info['fill']['filled_nodes']:,} grid nodes of empty space that the material "
                        f"encloses (holes up to ~{2 * cfg.fill_cavities} cells closed to tell; mesh.fill_cavities=0 "
                        "keeps the hollow)")
        t1 = time.perf_counter()
        vertices, faces = marching_cubes(grid, level, aabb)
        info["time_marching_cubes_s"] = round(time.perf_counter() - t1, 3)
    except ValueError as exc:
        raise ReconError(
            f"No surface could be extracted from the trained field: {exc} Check the training metrics "
            f"(03_field/metrics.json); set mesh.iso explicitly (e.g. --set mesh.iso=10) if the automatic level is wrong."
        ) from None
    del grid
    if len(faces) == 0:
        raise ReconError("Marching cubes found no surface at the chosen iso-level; lower mesh.iso or re-train.")
    return vertices, faces, info


def extract_zero_set(
    model: torch.nn.Module, aabb: torch.Tensor, shape: tuple[int, int, int], cfg: MeshConfig, report: Any,
    closed: bool = False, support: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """A surface field's zero level set: -f (positive inside) on the grid over aabb (2, 3), coarse to fine
    as `extract_mesh`, marching cubes at 0. The grid's outer node layer is set outside (f > 0), so the mesh
    is closed even where the object meets the box; ``closed`` also caps it on the ``support`` plane
    (`close_solid`: no views' inside and no ball, a signed distance has a real inside). Returns vertices (V, 3), faces (F, 3),
    info."""
    cell = float(grid_spacing(aabb, shape).max())
    mode, _ = extraction_mode(cfg.coarse_to_fine, shape)
    sparse_ok = mode == "coarse-to-fine"
    info: dict[str, Any] = {"grid": list(shape), "cell": cell, "mode": mode}

    def inside(x: torch.Tensor) -> torch.Tensor:
        return -model.sdf(x)

    t0 = time.perf_counter()
    with report.task("signed distance grid", total=None if sparse_ok else math.prod(shape), unit="points") as bar:
        if sparse_ok:
            grid, info["sparse"] = density_grid_sparse(_counting(inside, bar), aabb, shape, 0.0, coarse=COARSE_NODES,
                                                       chunk=DENSITY_CHUNK)
            info["evaluated"] = info["sparse"]["evaluated"]
        else:
            grid = density_grid(_counting(inside, bar), aabb, shape, chunk=DENSITY_CHUNK)
            info["evaluated"] = math.prod(shape)
    for axis in range(3):  # close the surface at the box: its faces count as outside
        idx: list[Any] = [slice(None)] * 3
        for end in (0, -1):
            idx[axis] = end
            np.minimum(grid[tuple(idx)], -0.5 * cell, out=grid[tuple(idx)])
    if closed:
        grid, info["fill"] = close_solid(grid, 0.0, aabb, support, 0)
    info["time_grid_s"] = round(time.perf_counter() - t0, 3)
    info["iso"], info["iso_reason"] = 0.0, "the signed distance's zero level set (surface field)"
    report.info(f"signed distance grid: {info['evaluated']:,} of {math.prod(shape):,} nodes evaluated in {info['time_grid_s']:.1f} s")
    if not grid.max() > 0:
        raise ReconError("The surface field has no inside (its signed distance is positive everywhere in the box); re-train it.")
    t1 = time.perf_counter()
    vertices, faces = marching_cubes(grid, 0.0, aabb)
    info["time_marching_cubes_s"] = round(time.perf_counter() - t1, 3)
    return vertices, faces, info
