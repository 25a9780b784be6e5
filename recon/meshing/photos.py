"""The trained field and its mesh seen from the photos' views: what the mesh stage checks and colours against.

The field's rendered depth in each view tells which faces some photo sees (`see_with_views`); the masks tell
which vertices are object (`inside_masks`); the mesh's own z-buffer in each view (`mesh_depths`) decides which
photo pixels colour a vertex or a texel (`bake_colors`, `texture_mesh`); `compare_in_views` scores the meshes
against held-out photos and `coherence` against the object's pixels and the SfM points. Views are
`recon.evaluation.views.View`s at training size; the array work is `recon.geometry`'s.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recon.camera import project
from recon.capture.scene import Frame, Scene, pinhole_mask, spread_evenly
from recon.config import MeshConfig
from recon.evaluation.views import View, load_views, render_view, target_rgb
from recon.geometry.clean import SeenFn
from recon.geometry.coherence import largest_piece, mesh_zbuffers, object_pixels, point_agreement, projected_coverage
from recon.geometry.color import colors_from_field, colors_from_photos, seen_by_views
from recon.geometry.extract import behind_views
from recon.geometry.raster import per_camera, render_mesh
from recon.geometry.texture import TexturedMesh, UnwrappedMesh, bake_unwrapped, unwrap_mesh

BAKE_TOL_FRACTION = 0.01
"""Depth tolerance of photo baking as a fraction of the mesh's bounding-box diagonal (`colors_from_photos`'
default), fixed once per mesh so vertices and texels are tested alike."""
COHERENCE_VIEWS = 8
"""Photos (spread evenly over those rendered for visibility) the mesh is rasterized into for its projected coverage."""
OBJECT_OPACITY = 0.5
"""A pixel shows a surface (for the coherence check) when the field renders it at least this opaque."""


def field_views(scene: Scene, frames: list[Frame], max_side: int, meta: dict[str, Any], report: Any) -> list[View]:
    """The frames' photos at training size as the field saw them: at the neutral appearance when it was trained
    with per-photo appearance (so every photo bakes the same colours), at the refined pose when training refined
    the poses (so each projects where the field saw it)."""
    views = load_views(scene, frames, max_side, report, "photos for visibility and colors")
    if meta.get("appearance"):
        from recon.nerf.appearance import to_neutral

        views = [dataclasses.replace(v, image=to_neutral(v.image, meta["appearance"].get(v.name))) for v in views]
    if meta.get("refined_c2w"):
        refined = meta["refined_c2w"]
        views = [dataclasses.replace(v, c2w=np.asarray(refined[v.name], np.float64)) if v.name in refined else v
                 for v in views]
    return views


# ---------------------------------------------------------------------------------------- the field's depth
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
        out = render_view(model, view, aabb, background, colors=False)
        if opacities is not None:
            opacities.append(out["opacity"])
        return out["depth"]
    h2, w2 = max(1, round(h * scale)), max(1, round(w * scale))
    sx, sy = w2 / w, h2 / h
    fx, fy, cx, cy = view.intrinsics
    small = View(view.name, np.zeros((h2, w2, 3), np.uint8), view.c2w, (fx * sx, fy * sy, cx * sx, cy * sy), view.near, view.far)
    out = render_view(model, small, aabb, background, colors=False)
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


# ---------------------------------------------------------------------------------------- cleaning
def see_with_views(views: Sequence[View], depths: Sequence[np.ndarray], tol: float,
                   device: torch.device | None = None) -> SeenFn:
    """``seen_fn`` of `clean_mesh`: how many of these views see each vertex (`seen_by_views` on their rendered depth),
    on a CUDA ``device`` every view at once; a CPU keeps the numpy loop, which is faster there."""
    on = device if device is not None and device.type == "cuda" else None

    def seen(vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return seen_by_views(vertices, normals, depths, np.stack([v.c2w for v in views]),
                             np.asarray([v.intrinsics for v in views], np.float64), tol, device=on)
    return seen


def hidden_from_views(views: Sequence[View], depths: Sequence[np.ndarray], opacities: Sequence[np.ndarray],
                      region: np.ndarray, tol: float) -> Callable[[tuple[int, int, int]], np.ndarray]:
    """``hidden`` of `extract_mesh`: the grid nodes over ``region`` (2, 3) that none of these views sees as empty
    (`behind_views`); a pixel less than OBJECT_OPACITY opaque shows no surface (its depth is the ray's far end)."""
    def hidden(shape: tuple[int, int, int]) -> np.ndarray:
        shown = [np.where(o >= OBJECT_OPACITY, d, np.inf) for d, o in zip(depths, opacities, strict=True)]
        return behind_views(region, shape, shown, np.stack([v.c2w for v in views]),
                            np.asarray([v.intrinsics for v in views], np.float64), tol)
    return hidden


Silhouette = tuple[np.ndarray, np.ndarray, Sequence[float]]
"""A photo's object mask as a pinhole image (H, W) bool, its camera's c2w (4, 4) and intrinsics (fl_x, fl_y, cx, cy)
at the mask's size."""


def _inside_silhouettes(silhouettes: Callable[[], Iterator[Silhouette]],
                        keep_fraction: float) -> Callable[[np.ndarray], np.ndarray]:
    """``keep_fn`` of `clean_mesh`: True for vertices (V, 3) inside the silhouettes of at least ``keep_fraction`` of
    the photos that frame them (or framed by none). A point of the object projects inside the object's silhouette in
    every photo, occluded or not, so no depth test is needed."""
    def keep(vertices: np.ndarray) -> np.ndarray:
        inside = np.zeros(len(vertices))
        framed = np.zeros(len(vertices))
        for mask, c2w, intrinsics in silhouettes():
            h, w = mask.shape
            uv, z = project(np.asarray(vertices, np.float64), c2w, intrinsics)
            ok = z > 1e-9
            u, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            ok &= (u >= 0) & (u < w) & (r >= 0) & (r < h)
            framed += ok
            inside[ok] += mask[r[ok], u[ok]]
        return (framed == 0) | (inside >= keep_fraction * framed)
    return keep


def inside_masks(views: Sequence[View], keep_fraction: float) -> Callable[[np.ndarray], np.ndarray]:
    """``keep_fn`` of `clean_mesh`: True for vertices (V, 3) that the masks (the views' alpha) call object in at least
    ``keep_fraction`` (mesh.mask_keep_fraction) of the photos that frame them, which leaves room for a pixel of mask
    edge."""
    return _inside_silhouettes(lambda: ((v.image[..., 3] >= 128, v.c2w, v.intrinsics) for v in views),
                               keep_fraction)


def inside_photo_masks(frames: Sequence[Frame], mask_folder: Path,
                       keep_fraction: float) -> Callable[[np.ndarray], np.ndarray]:
    """``keep_fn`` of `clean_mesh` from masks in ``mask_folder`` named like the photos (``<stem>.png``, white =
    object, at the photo's pixels: normalize's masks_unsure/): True for vertices (V, 3) that at least
    ``keep_fraction`` of the photos with a mask there call object. Each mask is read (and undistorted to a pinhole
    image, fisheyes too) when the keep_fn runs, one at a time (a clip's frames would not all fit in memory)."""
    def silhouettes() -> Iterator[Silhouette]:
        for frame in frames:
            path = mask_folder / f"{Path(frame.name).stem}.png"
            if path.is_file():
                yield pinhole_mask(path, frame, frame.w, frame.h), frame.c2w, frame.intrinsics_at(frame.w, frame.h)
    return _inside_silhouettes(silhouettes, keep_fraction)


# ---------------------------------------------------------------------------------------- coherence
def coherence(
    vertices: np.ndarray, faces: np.ndarray, views: Sequence[View], depths: Sequence[np.ndarray], region: np.ndarray,
    ground: np.ndarray | None, ground_layer: float, masked: bool, opacities: Sequence[np.ndarray] | None = None,
    seen_points: Sequence[np.ndarray] | None = None, point_tolerance: float = 0.0,
) -> dict:
    """Is the mesh one surface covering what the photos show of the object (`geometry.coherence`)? The object's
    pixels are the masks' (``masked``), else the pixels at least OBJECT_OPACITY opaque (``opacities``) whose rendered
    depth lands in the mesh region more than ``ground_layer`` above the ground (its table top's thickness). Without
    the opacity a transparent ray's depth is its exit from the scene box, which lies on the region's boundary when the
    region is the box, so the backdrop around the object would count as object. ``seen_points``: per view the SfM
    points it observes (those within ``ground_layer`` of the ground are the ground's); those in the mesh region are
    checked against the mesh (`point_agreement`, within ``point_tolerance``; None: the scene records no visibility,
    an import)."""
    out: dict[str, Any] = {"largest_piece": largest_piece(vertices, faces)}
    if not views:
        out["projected"] = None
        return out
    lo, hi = np.asarray(region, np.float64)

    def inside(p: np.ndarray) -> np.ndarray:
        ok = np.all((p >= lo) & (p <= hi), axis=1)
        return ok if ground is None else ok & (p @ ground[:3] - ground[3] >= ground_layer)

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


def describe_coherence(coherent: dict) -> str:
    """`coherence`'s checks in one sentence."""
    piece, proj, agree = coherent["largest_piece"], coherent["projected"], coherent.get("points")
    return (
        f"coherence: the largest of {piece['pieces']} piece(s) holds {piece['largest_area_fraction']:.1%} of the area"
        + (f"; in {len(proj['photos'])} photos the mesh covers {proj['coverage']:.1%} of the object's pixels "
           f"({proj['object']}), {proj['outside']:.1%} of its pixels lie outside them" if proj else "")
        + (f"; of the {agree['sightings']:,} sightings of SfM points in the mesh region in those photos, the mesh "
           f"passes within {agree['tolerance']:.3g} units of {agree['on']:.1%}, hides {agree['in_front']:.1%} "
           f"(mesh in front of a seen surface) and misses {agree['missing']:.1%}"
           if agree and agree["sightings"] else "")
    )


# ---------------------------------------------------------------------------------------- colors
def mesh_depths(vertices: np.ndarray, faces: np.ndarray, views: Sequence[View]) -> list[np.ndarray]:
    """The mesh's z-buffer in every view at the photo's size (`raster.mesh_depth`), what baking tests occlusion
    against: a vertex is seen where no other part of the mesh hides it. Pixels next to an empty one are emptied
    too (inf): at the silhouette the photo's pixel blends the object with what lies behind it."""
    from scipy.ndimage import maximum_filter

    zbuffers = mesh_zbuffers(vertices, faces, [(v.c2w, v.intrinsics, v.hw) for v in views])
    return [np.where(np.isinf(maximum_filter(z, size=3, mode="nearest")), np.inf, z) for z in zbuffers]


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
    device = next(model.parameters(), torch.empty(0)).device
    colors, seen = colors_from_photos(
        vertices,
        normals,
        [v.image for v in views],
        np.stack([v.c2w for v in views]),
        np.asarray([v.intrinsics for v in views], np.float64),
        depths=depths,
        depth_tol=depth_tol,
        depth_kind="z",
        device=device if device.type == "cuda" else None,  # a CPU keeps the numpy reference
    )
    if not seen.all():
        colors[~seen] = colors_from_field(model.radiance, vertices[~seen], normals[~seen], device=device)
    return colors, {"views": len(views), "seen": int(seen.sum()), "unseen_from_field": int((~seen).sum())}


# ---------------------------------------------------------------------------------------- textured mesh
def texture_mesh(
    model: torch.nn.Module, cfg: MeshConfig, views: Sequence[View], depths: Sequence[np.ndarray],
    vertices: np.ndarray, faces: np.ndarray, report: Any, side: int, unwrapped: UnwrappedMesh | None = None,
) -> TexturedMesh:
    """The mesh decimated to ``cfg.texture_faces``, unwrapped, with a ``side``² texture baked the
    way the vertex colors are (`bake_colors` on the surface point under each texel: the same depth test,
    median and field fallback; or the field's color with mesh.color=field). vertices, faces: the full mesh; depths:
    its z-buffer in each view (`mesh_depths`); unwrapped: its `unwrap_mesh` when the caller made it already."""
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

    if unwrapped is None:
        with report.task("texture: decimate, unwrap", total=None):
            unwrapped = unwrap_mesh(vertices, faces, cfg.texture_faces, side)
    with report.task(f"texture: bake {side}²", total=None, unit="texels") as bar:
        textured = bake_unwrapped(unwrapped, side, color_fn, progress=bar.advance)
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
    from recon.evaluation.metrics import mse_to_psnr

    def db(err: np.ndarray) -> float:
        return round(float(mse_to_psnr(float(np.mean(err)))), 3) if err.size else math.nan

    def compare(view: View) -> tuple[dict, np.ndarray]:
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
        gap = np.ones((gt.shape[0], 4, 3))
        return row, np.concatenate([gt, gap, vc, gap, tx], axis=1)

    with report.task(f"rendering the meshes into the {len(views)} held-out views", total=None):
        compared = per_camera(compare, views)
    per_view, strips = [row for row, _ in compared], [strip for _, strip in compared]
    keys = [k for k in per_view[0] if k.startswith("psnr")] if per_view else []
    metrics = {k: round(float(np.mean([v[k] for v in per_view])), 3) for k in keys}
    return {**metrics, "views": per_view}, strips
