"""mesh stage: the trained field → a cleaned, colored triangle mesh in glTF/OBJ/PLY, with a report.

Steps (each a function below, `run` only glues them and does the I/O):
1. `choose_resolution` (geometry.extract): grid nodes per axis from the pixel footprint at the cameras' median distance,
   capped by `mesh.max_resolution` and by `mesh.memory_budget_mb` (the float32 grid).
2. `extract_mesh`: σ grid over the scene box (coarse-to-fine or dense), iso-level, marching cubes.
3. `clean_mesh` (library): crop, drop floaters, drop the faces no photo sees (`see_with_views`), smooth, decimate.
4. `bake_colors` (photos, depth-tested against the field's rendered depth) or the field's colors.
5. `export_mesh` (library) in the normalized or the source frame, optionally scaled to a real size;
   `mesh_report.json`; two previews (`preview_front.png`, `preview_side.png`) from `render_preview` (geometry.preview),
   a z-buffered point splat of the colored mesh with Lambert shading (no OpenGL needed).
6. `texture_mesh` (with mesh.texture_faces > 0): a decimated, UV-unwrapped copy with its colors baked into a
   texture the same way (`mesh_textured.glb`, `.obj` + `.mtl` + `.png`); `compare_in_views` renders it and
   the vertex-colored mesh into the held-out photos' views (PSNR of each).
"""
from __future__ import annotations

import dataclasses
import math
import resource
import sys
import time
from typing import Any, Callable, Sequence

import numpy as np
import torch
import trimesh

from recon.atomic import write_json_atomic
from recon.config import MeshConfig, parse_region
from recon.errors import ReconError
from recon.field import load_field
from recon.geometry.clean import SeenFn, clean_mesh
from recon.geometry.coherence import largest_piece, mesh_zbuffers, object_pixels, point_agreement, projected_coverage
from recon.geometry.color import colors_from_field, colors_from_photos, seen_by_views
from recon.geometry.export import export_mesh, export_textured_mesh
from recon.geometry.extract import (
    auto_iso_level,
    choose_resolution,
    density_grid,
    density_grid_sparse,
    fill_enclosed,
    grid_spacing,
    marching_cubes,
)
from recon.geometry.preview import preview_camera, write_mesh_previews
from recon.normalization import box_corners
from recon.geometry.raster import mesh_depth, render_mesh
from recon.geometry.texture import TexturedMesh, make_textured_mesh
from recon.pipeline import Stage, StageContext
from recon.region import support_kind
from recon.scene import Frame, Scene, load_scene, spread_evenly
from recon.camera import pixel_footprint
from recon.views import View, load_views, render_view, target_rgb

REPORT_FILE = "mesh_report.json"
MESH_STEM = "mesh"
TEXTURED_STEM = "mesh_textured"
BAKE_TOL_FRACTION = 0.01
"""Depth tolerance of photo baking as a fraction of the mesh's bounding-box diagonal (`colors_from_photos`'
default), fixed once per mesh so vertices and texels are tested alike."""
COARSE_NODES = 64
"""Coarse grid nodes per axis: for coarse-to-fine refinement and for estimating the iso-level first."""
CPU_BAKE_VIEWS = {"fast": 24, "classic": 6}
"""On the CPU each baking view costs a render of its depth: at most this many views, spread evenly (the classic
NeRF renders about a hundred times slower than the fast model, so it gets fewer)."""
CPU_DEPTH_SIDE = {"fast": 200, "classic": 64}
"""On the CPU depth maps for baking are rendered at most this many pixels on the longest side."""
DENSITY_CHUNK = 2**16
"""Points per model.density call (the models are not chunked themselves)."""
HELD_OUT_VIEWS = 8
"""The textured and vertex-colored meshes are compared in at most this many held-out views (spread evenly)."""
HIDDEN_TOL_CELLS = 1.0
"""Depth tolerance of the hidden-face test in `surface_cell` units (the field's voxel for grid models). The
result is insensitive to it near one voxel: the inner walls lie several voxels behind the visible surface."""


# ---------------------------------------------------------------------------------------- resolution
def training_focal(frame: Frame, max_side: int) -> float:
    """Horizontal focal length (pixels) of a frame at the training resolution (photos downscaled to max_side)."""
    scale = min(1.0, max_side / max(frame.w, frame.h)) if max_side else 1.0
    return float(frame.fl_x * scale)


# ---------------------------------------------------------------------------------------- region
REGION_MARGIN = 0.1
"""The object region (sparse-point percentiles) is enlarged by this fraction of its size on each side."""
GROUND_MARGIN_CELLS = 2.0
"""Faces within this many surface cells (`surface_cell`) above the ground plane are cut with it: the field
makes a table top a layer about a voxel thick."""


def mesh_region(scene: Scene, aabb: np.ndarray, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray | None, str]:
    """The box to mesh (scene frame, inside aabb), the ground plane to cut (or None) and why.

    mesh.region auto: normalize's object region (what the cameras look at) grown by REGION_MARGIN, down to the
    ground; all: the whole scene box, nothing cut; a source-frame box: its bounding box in the scene frame.
    """
    choice = parse_region(cfg.region)
    aabb = np.asarray(aabb, np.float64)
    if choice == "all":
        return aabb, None, "the whole scene box (mesh.region=all)"
    ground = None if cfg.keep_ground or scene.ground is None else np.asarray(scene.ground, np.float64)
    ground_why = ""
    if scene.ground is not None:
        plane = "ground plane" if support_kind(scene.ground) == "ground" else "wall behind the object"
        ground_why = (f"; the {plane} is cut away (--set mesh.keep_ground=true keeps it)" if ground is not None
                      else f"; the {plane} is kept (mesh.keep_ground)")
    if choice == "auto":
        if scene.region is None:
            return aabb, ground, "the whole scene box (no object region was found)" + ground_why
        region = np.asarray(scene.region, np.float64)
        size = region[1] - region[0]
        box = region + np.stack([-size, size]) * REGION_MARGIN
        why = "the object the cameras look at (normalize's object region, +10%; --set mesh.region=all meshes everything)"
    else:
        corners = box_corners(np.asarray(choice, np.float64))
        T = scene.world_from_source
        mapped = corners @ T[:3, :3].T + T[:3, 3]
        box = np.stack([mapped.min(axis=0), mapped.max(axis=0)])
        why = f"the box {cfg.region} given in the source frame (mesh.region)"
    box = np.stack([np.maximum(box[0], aabb[0]), np.minimum(box[1], aabb[1])])
    if np.any(box[1] <= box[0]):
        raise ReconError(
            f"The mesh region ({cfg.region}) does not overlap the scene box {np.round(aabb, 3).tolist()}; give a box "
            f"inside the scene, or --set mesh.region=all."
        )
    return box, ground, why + ground_why


def capture_iso_opacity(cfg: MeshConfig, masked: bool) -> tuple[float, str]:
    """mesh.iso_opacity for this capture and why it differs from the setting ("" when it does not): as set, else
    MASKED_ISO_OPACITY with masks (they trained the background empty), else ISO_OPACITY (left to `auto_iso_level`)."""
    if cfg.iso_opacity or cfg.iso or not masked:
        return cfg.iso_opacity, ""
    return MASKED_ISO_OPACITY, (f"iso-level: one cell {MASKED_ISO_OPACITY:.0%} opaque (not {ISO_OPACITY:.0%}): the masks "
                                "trained the background empty, so a lower level closes holes without growing into it "
                                "(mesh.iso_opacity)")


def hollow_fill_applies(scene: Scene, cfg: MeshConfig, bounded: bool) -> tuple[bool, str]:
    """Whether mesh.fill_cavities applies, and why: it fills what an object's material encloses, so it runs when
    the mesh region is an object's (an object capture, normalize's object region, or a box given) and not on the
    whole box of an unbounded scene, whose walls, sky blobs and gaps enclose no object's inside (filling them
    there joins background into the mesh and splits its largest piece)."""
    if not cfg.fill_cavities:
        return False, ""
    choice = parse_region(cfg.region)
    if not bounded and (choice == "all" or (choice == "auto" and scene.region is None)):
        return False, ("hollow fill off: the mesh region is the whole scene box of an unbounded scene, not an object "
                       "(give mesh.region a box around the object to fill its hollow)")
    return True, ""


ISO_OPACITY = 0.35
"""One cell of material this opaque is surface (`auto_iso_level`), unless mesh.iso_opacity says otherwise. A field
is soft where few photos agree (fur, foliage, a facade at a slant, an undertrained patch): at 50% its mesh falls
into pieces and holes, at 25% it grows out of the surface; 35% keeps real captures in one piece without thickening
object captures (docs/real_captures.md)."""
MASKED_ISO_OPACITY = 0.25
"""The same with masks: the masked-out pixels trained the space around the object empty, so a lower level cannot
grow into the background; it closes the holes a soft, undertrained surface leaves (see MeshConfig.iso_opacity)."""

MASK_KEEP_FRACTION = 0.5
"""A vertex stays when it falls inside the object mask in at least this fraction of the photos that have it in frame."""


def inside_masks(views: Sequence[View]) -> Callable[[np.ndarray], np.ndarray]:
    """``keep_fn`` of `clean_mesh`: True for vertices (V, 3) that the masks (the views' alpha) call object.

    A point of the object projects inside the object's silhouette in every photo, occluded or not, so no depth
    test is needed; MASK_KEEP_FRACTION of the photos that frame it leaves room for a pixel of mask edge."""
    def keep(vertices: np.ndarray) -> np.ndarray:
        inside = np.zeros(len(vertices))
        framed = np.zeros(len(vertices))
        for v in views:
            h, w = v.hw
            fx, fy, cx, cy = v.intrinsics
            local = (np.asarray(vertices, np.float64) - v.c2w[:3, 3]) @ v.c2w[:3, :3]
            z = -local[:, 2]
            ok = z > 1e-9
            u = np.floor(cx + fx * local[:, 0] / np.where(ok, z, 1.0)).astype(np.int64)
            r = np.floor(cy - fy * local[:, 1] / np.where(ok, z, 1.0)).astype(np.int64)
            ok &= (u >= 0) & (u < w) & (r >= 0) & (r < h)
            framed += ok
            inside[ok] += v.image[r[ok], u[ok], 3] >= 128
        return (framed == 0) | (inside >= MASK_KEEP_FRACTION * framed)
    return keep


# ---------------------------------------------------------------------------------------- extraction
def _counting(density_fn: Callable[[torch.Tensor], torch.Tensor], bar: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """density_fn that advances a progress bar by the number of points it evaluated."""
    def fn(x: torch.Tensor) -> torch.Tensor:
        sigma = density_fn(x)
        bar.advance(int(x.shape[0]))
        return sigma

    return fn


def surface_cell(model: torch.nn.Module, aabb: np.ndarray | torch.Tensor, shape: tuple[int, int, int]) -> tuple[float, str]:
    """The finest layer thickness the mesh can trust (scene units) and why: the mesh grid's cell, or the
    field's own voxel (`voxel_size` of grid models) when that is coarser — a field cannot make material
    thinner than its voxel opaque, so an iso-level from a finer mesh cell would cut holes in its shell."""
    cell = float(grid_spacing(aabb, shape).max())
    voxel = float(getattr(model, "voxel_size", 0.0) or 0.0)
    if voxel > cell:
        return voxel, f"the field's voxel {voxel:.4g} (coarser than the mesh cell {cell:.4g})"
    return cell, f"the mesh cell {cell:.4g}"


def extract_mesh(
    model: torch.nn.Module, aabb: torch.Tensor, shape: tuple[int, int, int], cfg: MeshConfig, report: Any
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Density grid over aabb (2, 3) (on aabb's device) → iso-level → marching cubes.

    ``model.density(x (M, 3)) -> (M,)`` in 1/scene unit. Coarse-to-fine (``cfg.coarse_to_fine``) needs
    the level before the fine grid: it is estimated with `auto_iso_level` on a 64³ preview grid (same
    rule, `surface_cell`) unless ``cfg.iso > 0`` gives it; grids under 127 nodes a side are evaluated
    densely (a coarse block would be one cell, so refinement saves nothing). Returns vertices (V, 3)
    float32 and faces (F, 3) int64 in the scene frame, and info (grid, iso and its reason, counts, timings).
    """
    cell = float(grid_spacing(aabb, shape).max())
    iso_cell, iso_cell_why = surface_cell(model, aabb, shape)
    override = cfg.iso if cfg.iso > 0 else None
    # Refining pays only when a coarse block spans >= 2 fine cells; below that every node is coarse anyway.
    sparse_ok = max(shape) - 1 >= 2 * (COARSE_NODES - 1)
    mode = "coarse-to-fine" if cfg.coarse_to_fine and sparse_ok else "dense"
    info: dict[str, Any] = {"grid": list(shape), "cell": cell, "mode": mode}
    if cfg.coarse_to_fine and not sparse_ok:
        info["mode_reason"] = f"dense: the grid is too small (< {2 * COARSE_NODES - 1} nodes) for coarse-to-fine to save work"
    t0 = time.perf_counter()
    dense = math.prod(shape)
    try:
        if mode == "coarse-to-fine":
            n_preview = min(COARSE_NODES, max(shape))
            with report.task("density preview grid", total=n_preview**3, unit="points") as bar:
                preview = density_grid(_counting(model.density, bar), aabb, n_preview, chunk=DENSITY_CHUNK)
            level, why = auto_iso_level(preview, iso_cell, opacity=cfg.iso_opacity or ISO_OPACITY, override=override)
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
            level, why = auto_iso_level(grid, iso_cell, opacity=cfg.iso_opacity or ISO_OPACITY, override=override)
            if override is None:
                why += f"; cell: {iso_cell_why}"
            info["evaluated"] = dense
        info["time_grid_s"] = round(time.perf_counter() - t0, 3)
        info["iso"], info["iso_reason"] = float(level), why
        report.info(f"density grid: {info['evaluated']:,} of {dense:,} nodes evaluated in {info['time_grid_s']:.1f} s; {why}")
        if cfg.fill_cavities:
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
    model: torch.nn.Module, aabb: torch.Tensor, shape: tuple[int, int, int], cfg: MeshConfig, report: Any
) -> tuple[np.ndarray, np.ndarray, dict]:
    """A surface field's zero level set: -f (positive inside) on the grid over aabb (2, 3), coarse to fine
    as `extract_mesh`, marching cubes at 0. The grid's outer node layer is set outside (f > 0), so the mesh
    is closed even where the object meets the box. Returns vertices (V, 3), faces (F, 3), info."""
    cell = float(grid_spacing(aabb, shape).max())
    sparse_ok = cfg.coarse_to_fine and max(shape) - 1 >= 2 * (COARSE_NODES - 1)
    info: dict[str, Any] = {"grid": list(shape), "cell": cell, "mode": "coarse-to-fine" if sparse_ok else "dense"}

    def inside(x: torch.Tensor) -> torch.Tensor:
        return -model.sdf(x)

    t0 = time.perf_counter()
    with report.task("signed distance grid", total=None if sparse_ok else math.prod(shape), unit="points") as bar:
        if sparse_ok:
            grid, info["sparse"] = density_grid_sparse(_counting(inside, bar), aabb, shape, 0.0, coarse=COARSE_NODES, chunk=DENSITY_CHUNK)
            info["evaluated"] = info["sparse"]["evaluated"]
        else:
            grid = density_grid(_counting(inside, bar), aabb, shape, chunk=DENSITY_CHUNK)
            info["evaluated"] = math.prod(shape)
    for axis in range(3):  # close the surface at the box: its faces count as outside
        idx: list[Any] = [slice(None)] * 3
        for end in (0, -1):
            idx[axis] = end
            np.minimum(grid[tuple(idx)], -0.5 * cell, out=grid[tuple(idx)])
    info["time_grid_s"] = round(time.perf_counter() - t0, 3)
    info["iso"], info["iso_reason"] = 0.0, "the signed distance's zero level set (surface field)"
    report.info(f"signed distance grid: {info['evaluated']:,} of {math.prod(shape):,} nodes evaluated in {info['time_grid_s']:.1f} s")
    if not grid.max() > 0:
        raise ReconError("The surface field has no inside (its signed distance is positive everywhere in the box); re-train it.")
    t1 = time.perf_counter()
    vertices, faces = marching_cubes(grid, 0.0, aabb)
    info["time_marching_cubes_s"] = round(time.perf_counter() - t1, 3)
    return vertices, faces, info


# ---------------------------------------------------------------------------------------- coherence
COHERENCE_VIEWS = 8
"""Photos (spread evenly over those rendered for visibility) the mesh is rasterized into for its projected coverage."""


POINT_TOL_CELLS = 1.0
"""The mesh passes through an SfM point (coherence's point agreement) when within this many field voxels of it."""


OBJECT_OPACITY = 0.5
"""A pixel shows a surface (for the coherence check) when the field renders it at least this opaque."""


def coherence(
    vertices: np.ndarray, faces: np.ndarray, views: Sequence[View], depths: Sequence[np.ndarray], region: np.ndarray,
    ground: np.ndarray | None, ground_margin: float, masked: bool, opacities: Sequence[np.ndarray] | None = None,
    seen_points: Sequence[np.ndarray] | None = None, point_tolerance: float = 0.0,
) -> dict:
    """Is the mesh one surface covering what the photos show of the object (`geometry.coherence`)? The object's
    pixels are the masks' (``masked``), else the pixels at least OBJECT_OPACITY opaque (``opacities``) whose rendered
    depth lands in the mesh region above the cut ground. Without the opacity a transparent ray's depth is its exit
    from the scene box, which lies on the region's boundary when the region is the box: the surface model's runs
    then counted the backdrop around the object as object and read 48-63% coverage. ``seen_points``: per view the
    SfM points it observes; those in the mesh region are checked against the mesh (`point_agreement`, within
    ``point_tolerance``; None: the scene records no visibility, an import)."""
    out: dict[str, Any] = {"largest_piece": largest_piece(vertices, faces)}
    if not views:
        out["projected"] = None
        return out
    lo, hi = np.asarray(region, np.float64)

    def inside(p: np.ndarray) -> np.ndarray:
        ok = np.all((p >= lo) & (p <= hi), axis=1)
        return ok if ground is None else ok & (p @ ground[:3] - ground[3] >= ground_margin)

    pick = spread_evenly(list(range(len(views))), COHERENCE_VIEWS)
    cams = [(views[i].c2w, views[i].intrinsics, views[i].hw) for i in pick]
    def surface_depth(i: int) -> np.ndarray:
        return depths[i] if opacities is None else np.where(opacities[i] >= OBJECT_OPACITY, depths[i], np.inf)

    objects = [views[i].image[..., 3] >= 128 if masked else object_pixels(views[i].c2w, views[i].intrinsics, surface_depth(i), inside)
               for i in pick]
    zbuffers = mesh_zbuffers(vertices, faces, cams)
    proj = projected_coverage(zbuffers, objects)
    proj["object"] = "the photos' masks" if masked else "pixels whose rendered depth lies in the mesh region (above the cut ground)"
    proj["photos"] = [views[i].name for i in pick]
    out["projected"] = proj
    if seen_points is not None:
        kept = [np.asarray(seen_points[i], np.float64).reshape(-1, 3) for i in pick]
        out["points"] = point_agreement(zbuffers, cams, [p[inside(p)] for p in kept], point_tolerance)
    return out


# ---------------------------------------------------------------------------------------- colors
def render_depth(
    model: torch.nn.Module, view: View, aabb: torch.Tensor | None, background: np.ndarray, max_side: int | None = None,
    opacities: list[np.ndarray] | None = None,
) -> np.ndarray:
    """Expected ray distance (H, W) of the view at its own size, rendered at most ``max_side`` pixels
    on the longest side and upsampled nearest (each full-size pixel takes the low-res pixel it lies in).
    A transparent ray reads its far end (the models place the remainder there); pass ``opacities`` to get each
    pixel's opacity (H, W) appended to it, to tell such rays apart."""
    h, w = view.hw
    scale = min(1.0, max_side / max(h, w)) if max_side else 1.0
    if scale >= 1.0:
        out = render_view(model, view, aabb, background)
        if opacities is not None:
            opacities.append(out["opacity"])
        return out["depth"]
    h2, w2 = max(1, round(h * scale)), max(1, round(w * scale))
    sx, sy = w2 / w, h2 / h
    fx, fy, cx, cy = view.intrinsics
    small = View(view.name, np.zeros((h2, w2, 3), np.uint8), view.c2w, (fx * sx, fy * sy, cx * sx, cy * sy), view.near, view.far)
    out = render_view(model, small, aabb, background)
    rows = np.minimum(((np.arange(h) + 0.5) * sy).astype(np.int64), h2 - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * sx).astype(np.int64), w2 - 1)
    if opacities is not None:
        opacities.append(out["opacity"][rows[:, None], cols[None, :]])
    return out["depth"][rows[:, None], cols[None, :]]


def render_depths(
    model: torch.nn.Module, views: Sequence[View], aabb: torch.Tensor | None, background: np.ndarray,
    max_side: int | None, report: Any, opacities: list[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Depth map of every view (`render_depth`), with a progress bar: shared by the hidden-face test and baking
    (and their opacities appended to ``opacities`` when given, for the coherence check)."""
    depths = []
    with report.task("rendering depth of the photos' views", total=len(views), unit="views") as bar:
        for v in views:
            depths.append(render_depth(model, v, aabb, background, max_side, opacities))
            bar.advance()
    return depths


def see_with_views(views: Sequence[View], depths: Sequence[np.ndarray], tol: float) -> SeenFn:
    """``seen_fn`` of `clean_mesh`: how many of these views see each vertex (`seen_by_views` on their rendered depth)."""
    def seen(vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return seen_by_views(vertices, normals, depths, np.stack([v.c2w for v in views]),
                             np.asarray([v.intrinsics for v in views], np.float64), tol)
    return seen


def mesh_depths(vertices: np.ndarray, faces: np.ndarray, views: Sequence[View]) -> list[np.ndarray]:
    """The mesh's z-buffer in every view at the photo's size (`raster.mesh_depth`), what baking tests occlusion
    against: a vertex is seen where no other part of the mesh hides it. Pixels next to an empty one are emptied
    too (inf): at the silhouette the photo's pixel blends the object with what lies behind it."""
    from scipy.ndimage import maximum_filter

    out = []
    for v in views:
        z = mesh_depth(vertices, faces, v.c2w, v.intrinsics, v.hw)
        out.append(np.where(np.isinf(maximum_filter(z, size=3, mode="nearest")), np.inf, z))
    return out


def bake_colors(
    model: torch.nn.Module,
    views: Sequence[View],
    depths: Sequence[np.ndarray],
    vertices: np.ndarray,
    normals: np.ndarray,
    depth_tol: float | None = None,
) -> tuple[np.ndarray, dict]:
    """Vertex colors (V, 3) float32 sRGB from the photos, occlusion-tested against the mesh's own z-buffer.

    ``depths``: the mesh's z-buffer per view (`mesh_depths`); `colors_from_photos` keeps the samples whose vertex
    depth matches it within depth_tol (default: `BAKE_TOL_FRACTION` of the vertices' bounding-box diagonal).
    Vertices no view sees take the field's color.
    vertices, normals: (V, 3) scene frame (or texel points, `texture_mesh`), normals outward; views:
    photos at training size (uint8 images, OpenGL c2w).
    """
    if depth_tol is None:
        depth_tol = BAKE_TOL_FRACTION * float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
    colors, seen = colors_from_photos(
        vertices,
        normals,
        [v.image for v in views],
        np.stack([v.c2w for v in views]),
        np.asarray([v.intrinsics for v in views], np.float64),
        depths=depths,
        depth_tol=depth_tol,
        depth_kind="z",
    )
    device = next(model.parameters(), torch.empty(0)).device
    if not seen.all():
        colors[~seen] = colors_from_field(model.radiance, vertices[~seen], normals[~seen], device=device)
    return colors, {"views": len(views), "seen": int(seen.sum()), "unseen_from_field": int((~seen).sum())}


# ---------------------------------------------------------------------------------------- textured mesh
def texture_mesh(
    model: torch.nn.Module, cfg: MeshConfig, views: Sequence[View], depths: Sequence[np.ndarray],
    vertices: np.ndarray, faces: np.ndarray, report: Any,
) -> TexturedMesh:
    """The mesh decimated to ``cfg.texture_faces``, unwrapped, with a ``cfg.texture_size``² texture baked the
    way the vertex colors are (`bake_colors` on the surface point under each texel: the same depth test,
    median and field fallback; or the field's color with mesh.color=field). vertices, faces: the full mesh; depths:
    its z-buffer in each view (`mesh_depths`)."""
    device = next(model.parameters(), torch.empty(0)).device
    unseen = [0]
    if cfg.color == "photos":
        tol = BAKE_TOL_FRACTION * float(np.linalg.norm(np.ptp(vertices, axis=0)))

        def color_fn(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            colors, info = bake_colors(model, views, depths, points, normals, depth_tol=tol)
            unseen[0] += info["unseen_from_field"]
            return colors
    else:
        def color_fn(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            return colors_from_field(model.radiance, points, normals, device=device)

    with report.task(f"texture: decimate, unwrap, bake {cfg.texture_size}²", total=None, unit="texels") as bar:
        textured = make_textured_mesh(vertices, faces, cfg.texture_faces, cfg.texture_size, color_fn, progress=bar.advance)
    textured.info["source"] = cfg.color
    if cfg.color == "photos":
        textured.info["unseen_from_field"] = unseen[0]
    return textured


def compare_in_views(
    views: Sequence[View], background: np.ndarray, vertex_mesh: tuple[np.ndarray, np.ndarray, np.ndarray],
    textured: TexturedMesh, report: Any, light_colors: np.ndarray | None = None,
) -> tuple[dict, list[np.ndarray]]:
    """PSNR against the photos of the vertex-colored mesh (vertices, faces, colors) and of the textured mesh,
    each rendered unlit (`raster.render_mesh`) into every view on the field's background: over the whole
    photo, and over the pixels both meshes cover (the colors alone, without the silhouettes). With
    ``light_colors`` (V, 3) for the textured mesh's vertices, also that light mesh with vertex colors instead
    of the texture ("light_vertex_colors": what the texture buys at the same face count).
    Returns the metrics and, per view, a strip photo | vertex colors | texture (H, 3W + 8, 3) in [0, 1]."""
    from recon.metrics import mse_to_psnr

    def db(err: np.ndarray) -> float:
        return round(float(mse_to_psnr(float(np.mean(err)))), 3) if err.size else math.nan

    per_view, strips = [], []
    with report.task("rendering the meshes into the held-out views", total=len(views), unit="views") as bar:
        for view in views:
            gt = target_rgb(view, background)[..., :3]
            cam = (view.c2w, view.intrinsics, view.hw)
            vc, vc_mask = render_mesh(*vertex_mesh[:2], *cam, colors=vertex_mesh[2], background=background)
            tx, tx_mask = render_mesh(textured.vertices, textured.faces, *cam, uv=textured.uv, texture=textured.texture,
                                      background=background)
            both = vc_mask & tx_mask
            row = {"view": view.name,
                   "psnr_vertex_colors": db((vc - gt) ** 2), "psnr_textured": db((tx - gt) ** 2),
                   "psnr_vertex_colors_covered": db((vc - gt)[both] ** 2), "psnr_textured_covered": db((tx - gt)[both] ** 2),
                   "covered_fraction": round(float(both.mean()), 4)}
            if light_colors is not None:
                lv, _ = render_mesh(textured.vertices, textured.faces, *cam, colors=light_colors, background=background)
                row["psnr_light_vertex_colors"] = db((lv - gt) ** 2)
                row["psnr_light_vertex_colors_covered"] = db((lv - gt)[both] ** 2)
            per_view.append(row)
            gap = np.ones((gt.shape[0], 4, 3))
            strips.append(np.concatenate([gt, gap, vc, gap, tx], axis=1))
            bar.advance()
    keys = [k for k in per_view[0] if k.startswith("psnr")] if per_view else []
    metrics = {k: round(float(np.mean([v[k] for v in per_view])), 3) for k in keys}
    return {**metrics, "views": per_view}, strips


def preview_textured(textured: TexturedMesh, size: int = 512, azimuth_deg: float = 0.0, elevation_deg: float = 20.0) -> np.ndarray:
    """Unlit render (size, size, 3) in [0, 1] of the textured mesh on white, from `render_preview`'s camera
    (`preview_camera`; azimuth 0: from -Y, 20° up), the whole mesh in view."""
    c2w, intrinsics = preview_camera(textured.vertices, size, azimuth_deg, elevation_deg)
    rgb, _ = render_mesh(textured.vertices, textured.faces, c2w, intrinsics, (size, size),
                         uv=textured.uv, texture=textured.texture)
    return rgb


# ---------------------------------------------------------------------------------------- export frame
def export_transform(
    vertices: np.ndarray, frame: str, source_from_world: np.ndarray, real_size: float
) -> tuple[np.ndarray | None, str]:
    """4×4 scene → output-frame transform (None: identity) and its description.

    frame "normalized" keeps our frame, "source" maps back with ``source_from_world`` (the exact
    inverse normalization similarity). ``real_size > 0`` then scales about the frame's origin so
    the largest bounding-box side of vertices (V, 3) is ``real_size`` units.
    """
    if frame not in ("normalized", "source"):
        raise ReconError(f"mesh.frame must be 'normalized' or 'source', got '{frame}'.")
    transform = np.asarray(source_from_world, np.float64) if frame == "source" else np.eye(4)
    why = "source frame (inverse of the normalization similarity)" if frame == "source" else "normalized scene frame (+Z up)"
    if real_size > 0:
        mapped = np.asarray(vertices, np.float64) @ transform[:3, :3].T + transform[:3, 3]
        side = float(np.ptp(mapped, axis=0).max())
        if side <= 0:
            raise ReconError("The mesh has no extent; mesh.real_size cannot scale it.")
        transform = np.diag([real_size / side] * 3 + [1.0]) @ transform
        why += f", scaled ×{real_size / side:.6g} so the largest side is {real_size:g} units"
    return (None if np.allclose(transform, np.eye(4)) else transform), why


# ---------------------------------------------------------------------------------------- the stage
def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (ru_maxrss is KiB on Linux, bytes on macOS)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 1024


def _scene_footprint(scene: Scene, frames: list[Frame], aabb: np.ndarray, max_side: int) -> tuple[float, str]:
    centres = np.stack([f.c2w[:3, 3] for f in frames])
    focals = np.array([training_focal(f, max_side) for f in frames])
    fp, dist = pixel_footprint(aabb, centres, focals)
    return fp, f" (median camera distance {dist:.3g}, focal {np.median(focals):.1f} px at training size {max_side})"


def run(ctx: StageContext) -> dict:
    from recon.nerf.device import select_device

    cfg: MeshConfig = ctx.config
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    try:
        device = select_device(ctx.run_config.train.device)  # the device training used, as the user chose it
    except ValueError as exc:
        raise ReconError(f"train.device={ctx.run_config.train.device}: {exc}") from None
    scene = load_scene(ctx.inputs["normalize"])
    model, meta = load_field(ctx.inputs["train"], device)
    aabb = np.asarray(meta.get("aabb", scene.aabb), np.float64)
    aabb_t = torch.tensor(aabb, dtype=torch.float32, device=device)
    max_side = int(meta.get("max_side", 400))
    background = np.asarray(meta.get("background", [1.0, 1.0, 1.0]), np.float32)
    train_frames = scene.split("train") or scene.frames
    if not meta.get("bounded", True):
        ctx.report.info("unbounded scene: the mesh covers the scene box only (the background is not meshed)")

    region, ground, region_why = mesh_region(scene, aabb, cfg)
    ctx.report.info(f"mesh region: {region_why}")
    region_t = torch.tensor(region, dtype=torch.float32, device=device)
    footprint, fp_why = (None, "") if cfg.resolution > 0 else _scene_footprint(scene, train_frames, aabb, max_side)
    shape, res_why = choose_resolution(region, cfg, footprint, fp_why)
    ctx.report.info(f"resolution: {res_why}")

    surface = meta.get("kind") == "surface"  # an SDF: its zero level set is closed, no hidden faces to drop
    kind = "classic" if meta.get("kind") == "classic" else "fast"
    drop_hidden = cfg.drop_hidden and not surface
    bounded = meta.get("bounded", True)
    views: list[View] = []
    view_frames: list[Frame] = []
    depths: list[np.ndarray] = []
    opacities: list[np.ndarray] = []
    masked = bool(train_frames) and all(f.mask_path for f in train_frames)
    if cfg.color == "photos" or drop_hidden or masked:
        t = time.perf_counter()
        limit = CPU_BAKE_VIEWS[kind] if device.type == "cpu" else 0
        depth_side = CPU_DEPTH_SIDE[kind] if device.type == "cpu" else None
        view_frames = spread_evenly(train_frames, limit)
        views = load_views(scene, view_frames, max_side, ctx.report, "photos for visibility and colors")
        if meta.get("appearance"):  # trained with per-photo appearance: bake every photo at the neutral one
            from dataclasses import replace

            from recon.nerf.appearance import to_neutral

            views = [replace(v, image=to_neutral(v.image, meta["appearance"].get(v.name))) for v in views]
        if meta.get("refined_c2w"):  # training refined the photos' poses: project them where the field saw them
            refined = meta["refined_c2w"]
            views = [dataclasses.replace(v, c2w=np.asarray(refined[v.name], np.float64)) if v.name in refined else v
                     for v in views]
        depths = render_depths(model, views, aabb_t if bounded else None, background, depth_side, ctx.report, opacities)
        timings["depth_s"] = round(time.perf_counter() - t, 3)
        view_note = f"{len(views)} of {len(train_frames)} training views"
        if len(views) < len(train_frames):
            view_note += f" (spread evenly; at most {limit} on the CPU for the {meta.get('kind', kind)} model, each costs a depth render)"
        if depth_side:
            view_note += f", depth rendered at ≤ {depth_side} px"

    if not surface:  # the SDF's zero set needs neither choice
        opacity, why = capture_iso_opacity(cfg, masked)
        if opacity != cfg.iso_opacity:
            cfg = dataclasses.replace(cfg, iso_opacity=opacity)
            ctx.report.info(why)
        fill, why = hollow_fill_applies(scene, cfg, bounded)
        if not fill and cfg.fill_cavities:
            cfg = dataclasses.replace(cfg, fill_cavities=0)
            ctx.report.info(why)
    t = time.perf_counter()
    vertices, faces, extract = (extract_zero_set if surface else extract_mesh)(model, region_t, shape, cfg, ctx.report)
    timings["extract_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    seen_fn = None
    if drop_hidden:
        hidden_tol = HIDDEN_TOL_CELLS * surface_cell(model, region, shape)[0]
        seen_fn = see_with_views(views, depths, hidden_tol)
    vertices, faces, clean = clean_mesh(
        vertices, faces, region,
        min_component_fraction=cfg.min_component_fraction,
        smooth_iters=cfg.smooth_iters,
        target_faces=cfg.target_faces or None,
        seen_fn=seen_fn,
        ground=ground,
        ground_margin=GROUND_MARGIN_CELLS * surface_cell(model, region, shape)[0],
        keep_fn=inside_masks(views) if masked else None,
    )
    timings["clean_s"] = round(time.perf_counter() - t, 3)
    if len(faces) == 0:
        raise ReconError("Every piece of the extracted surface was removed while cleaning; lower mesh.min_component_fraction.")
    removed = clean["components"]["removed"]
    ctx.report.info(f"cleaning: {clean['components']['rule']}: {removed} of {clean['components']['components']} pieces removed")
    if "masked" in clean:
        ctx.report.info(f"masks: {clean['masked']['faces_removed']:,} faces outside the object masks removed ({len(views)} photos)")
    if "ground_cut" in clean:
        kind = support_kind(ground)
        where = "on or below the ground plane" if kind == "ground" else "on or behind the wall"
        ctx.report.info(f"{kind}: {clean['ground_cut']['faces_removed']:,} faces {where} cut away")
    if "hidden" in clean:
        h = clean["hidden"]
        ctx.report.info(f"hidden faces: {h['removed_faces']:,} faces that no photo sees removed (inner walls of the field; "
                        f"{len(views)} views, depth tolerance {hidden_tol:.3g} units)")

    t = time.perf_counter()
    cell = surface_cell(model, region, shape)[0]
    observed = ([np.zeros((0, 3)) if p is None else p for p in map(scene.observed_points, view_frames)]
                if scene.point_visibility else None)
    coherent = coherence(vertices, faces, views, depths, region, ground, GROUND_MARGIN_CELLS * cell, masked,
                         opacities or None, observed, POINT_TOL_CELLS * cell)
    timings["coherence_s"] = round(time.perf_counter() - t, 3)
    piece, proj = coherent["largest_piece"], coherent["projected"]
    agree = coherent.get("points")
    ctx.report.info(
        f"coherence: the largest of {piece['pieces']} piece(s) holds {piece['largest_area_fraction']:.1%} of the area"
        + (f"; in {len(proj['photos'])} photos the mesh covers {proj['coverage']:.1%} of the object's pixels "
           f"({proj['object']}), {proj['outside']:.1%} of its pixels lie outside them" if proj else "")
        + (f"; of the {agree['sightings']:,} sightings of SfM points in the mesh region in those photos, the mesh "
           f"passes within {agree['tolerance']:.3g} units of {agree['on']:.1%}, hides {agree['in_front']:.1%} "
           f"(mesh in front of a seen surface) and misses {agree['missing']:.1%}"
           if agree and agree["sightings"] else "")
    )

    t = time.perf_counter()
    normals = np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, np.float32)
    surface_depths: list[np.ndarray] = []
    if cfg.color == "photos":
        surface_depths = mesh_depths(vertices, faces, views)
        colors, color_info = bake_colors(model, views, surface_depths, vertices, normals)
        color_info["source"] = "photos"
        note = (f"baked from {view_note}, each photo's pixel taken where no other part of the mesh hides the vertex; "
                f"{color_info['unseen_from_field']:,} unseen vertices colored by the field")
        color_info["note"] = note
    else:
        colors = colors_from_field(model.radiance, vertices, normals, device=device)
        color_info = {"source": "field", "note": "queried from the field, viewed head-on (d = -normal)"}
    ctx.report.info(f"colors: {color_info['note']}")
    timings["color_s"] = round(time.perf_counter() - t, 3)

    t = time.perf_counter()
    transform, frame_why = export_transform(vertices, cfg.frame, scene.source_from_world, cfg.real_size)
    paths = export_mesh(vertices, faces, colors, ctx.out, stem=MESH_STEM, transform=transform)
    previews = write_mesh_previews(vertices, faces, colors, ctx.out)
    timings["export_s"] = round(time.perf_counter() - t, 3)

    textured_info: dict[str, Any] | None = None
    if cfg.texture_faces:
        try:
            textured_info, texture_previews = _textured(ctx, cfg, scene, model, views, surface_depths, vertices, faces,
                                                        colors, transform, max_side, background, timings)
            previews += texture_previews
        except Exception as exc:  # an optional output: the vertex-colored mesh above is the stage's result
            textured_info = textured_failed(exc, cfg, ctx)
    timings["total_s"] = round(time.perf_counter() - t_all, 3)

    out = clean["output"]
    report = {
        "vertices": out["vertices"],
        "faces": out["faces"],
        "watertight": out["watertight"],
        "components_removed": removed,
        "component_rule": clean["components"]["rule"],
        "bbox_scene": out["bbox"],
        "resolution": {"grid": list(shape), "reason": res_why, "pixel_footprint": footprint},
        "region": {"box": region.tolist(), "reason": region_why, "ground": None if ground is None else ground.tolist()},
        "extraction": extract,
        "iso": extract["iso"],
        "iso_reason": extract["iso_reason"],
        "clean": clean,
        "coherence": coherent,
        "colors": color_info,
        "export": {
            "frame": cfg.frame,
            "reason": frame_why,
            "transform": (transform if transform is not None else np.eye(4)).tolist(),
            "transform_note": "maps the normalized scene frame (+Z up) to the exported frame, before the up-axis change",
            "files": {k: p.name for k, p in paths.items()},
            "axes": {"glb": "+Y up (scene +Z rotated -90° about X)", "obj": "+Y up", "ply": "+Z up (the exported frame itself)"},
        },
        "textured": textured_info,
        "previews": previews,
        "device": str(device),
        "timings_s": timings,
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }
    write_json_atomic(ctx.out / REPORT_FILE, report)
    return {
        "headline": (
            f"{out['vertices']:,} vertices, {out['faces']:,} faces, "
            f"{'watertight' if out['watertight'] else 'not watertight'}, {removed} floating piece(s) removed"
        ),
        "vertices": out["vertices"],
        "faces": out["faces"],
        "watertight": out["watertight"],
        "components_removed": removed,
        "grid": list(shape),
        "iso": round(extract["iso"], 4),
        "colors": color_info["note"],
        **({"textured": _textured_summary(textured_info)} if textured_info else {}),
    }


def _textured(
    ctx: StageContext, cfg: MeshConfig, scene: Scene, model: torch.nn.Module, views: list[View], depths: list[np.ndarray],
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, transform: np.ndarray | None, max_side: int,
    background: np.ndarray, timings: dict[str, float],
) -> tuple[dict, list[str]]:
    """`texture_mesh`, its files, preview, and `compare_in_views` in the held-out views: the report's "textured"."""
    from PIL import Image

    t = time.perf_counter()
    textured = texture_mesh(model, cfg, views, depths, vertices, faces, ctx.report)
    paths = export_textured_mesh(textured.vertices, textured.faces, textured.uv, textured.texture, ctx.out,
                                 stem=TEXTURED_STEM, normals=textured.normals, transform=transform)
    Image.fromarray(np.round(preview_textured(textured) * 255).astype(np.uint8)).save(ctx.out / "preview_textured.png")
    timings["texture_s"] = round(time.perf_counter() - t, 3)
    info: dict[str, Any] = {**textured.info, "files": {k: p.name for k, p in paths.items()}}
    previews = ["preview_textured.png"]
    ctx.report.info(
        f"textured mesh: {info['faces']:,} faces (decimated from {info['faces_in']:,}), {cfg.texture_size}² texture, "
        f"{info['coverage']:.0%} of its texels on the surface, baked like the vertex colors"
        + (f" ({info['unseen_from_field']:,} texels no photo sees colored by the field)" if "unseen_from_field" in info else "")
    )
    held_out = scene.split("test")
    if not held_out:
        info["held_out"] = None
        ctx.report.info("textured mesh: no held-out photos in the scene's split, so no PSNR against photos")
        return info, previews
    t = time.perf_counter()
    chosen = spread_evenly(held_out, HELD_OUT_VIEWS)
    test_views = load_views(scene, chosen, max_side, ctx.report, "held-out photos")
    light_colors = None
    if cfg.color == "photos":  # the same light mesh with vertex colors: what the texture adds at its face count
        light_colors = bake_colors(model, views, depths, textured.vertices, textured.normals)[0]
    info["held_out"], strips = compare_in_views(test_views, background, (vertices, faces, colors), textured, ctx.report,
                                                light_colors)
    Image.fromarray(np.round(np.clip(strips[0], 0, 1) * 255).astype(np.uint8)).save(ctx.out / "texture_compare.png")
    previews.append("texture_compare.png")
    timings["held_out_s"] = round(time.perf_counter() - t, 3)
    h = info["held_out"]
    ctx.report.info(
        f"held-out photos ({len(test_views)} of {len(held_out)}{', spread evenly' if len(chosen) < len(held_out) else ''}): "
        f"PSNR vertex colors {h['psnr_vertex_colors']:.2f} dB, textured {h['psnr_textured']:.2f} dB "
        f"(where both cover: {h['psnr_vertex_colors_covered']:.2f} / {h['psnr_textured_covered']:.2f} dB)"
        + (f"; the light mesh with vertex colors instead: {h['psnr_light_vertex_colors']:.2f} dB "
           f"({h['psnr_light_vertex_colors_covered']:.2f} dB where both cover)" if "psnr_light_vertex_colors" in h else "")
    )
    return info, previews


TEXTURED_OUTPUTS = ("preview_textured.png", "texture_compare.png")
"""The textured mesh's previews (besides its TEXTURED_STEM.* files): removed with them when texturing fails."""


def textured_failed(exc: Exception, cfg: MeshConfig, ctx: StageContext) -> dict[str, Any]:
    """The report's "textured" when unwrapping, baking or exporting the textured mesh failed: the error and what
    to do, said in one warning line; its partial files are removed so no half-written textured mesh is left.

    Why: the textured mesh is optional; the vertex-colored mesh (mesh.glb) is already written and is delivered."""
    for path in [*ctx.out.glob(f"{TEXTURED_STEM}.*"), *(ctx.out / name for name in TEXTURED_OUTPUTS)]:
        path.unlink(missing_ok=True)
    error = f"{type(exc).__name__}: {exc}"
    todo = (f"the vertex-colored {MESH_STEM}.glb is complete; for a textured mesh rerun the mesh stage with a larger "
            f"--set mesh.texture_size (now {cfg.texture_size}) or fewer --set mesh.texture_faces (now {cfg.texture_faces}), "
            f"or --set mesh.texture_faces=0 to skip it")
    ctx.report.warn(f"textured mesh not written ({error}); {todo}")
    return {"failed": True, "error": error, "what_to_do": todo, "texture_size": cfg.texture_size,
            "texture_faces": cfg.texture_faces}


def _textured_summary(info: dict) -> str:
    if info.get("failed"):
        return f"failed ({info['error']}), see mesh_report.json"
    text = f"{info['faces']:,} faces, {info['texture_size']}² texture"
    if info.get("held_out"):
        h = info["held_out"]
        text += f"; held-out PSNR {h['psnr_textured']:.2f} dB (vertex colors {h['psnr_vertex_colors']:.2f} dB)"
    return text


# version 4: zero-area faces marching cubes leaves stay (dropping one opened a three-edge hole in a closed zero set)
STAGE = Stage(name="mesh", folder="04_mesh", inputs=("normalize", "train"), version=4, run=run)
