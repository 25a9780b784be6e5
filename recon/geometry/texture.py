"""A light textured mesh from a dense one: UV unwrap (xatlas), the surface point under every texel, baking
colors into a texture image, and padding the islands' seams.

Why: vertex colors need about a million vertices to look sharp; a 50k-face mesh with a 2048² texture keeps
the photos' detail in the image instead of the geometry, and it is what Blender and game engines expect.

Conventions: UVs are OpenGL/OBJ style (u right, v up, origin at the image's bottom-left); a texture is an
(H, W, C) image stored top row first, so texel (row r, column c) has its centre at
u = (c + 0.5) / W, v = 1 − (r + 0.5) / H (`raster.uv_to_pixels` maps the other way).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt

from recon.geometry.atlas_child import in_child
from recon.geometry.clean import decimate
from recon.geometry.raster import interpolate, rasterize, uv_to_pixels

ColorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``color_fn(points (N, 3), normals (N, 3) outward unit) -> (N, 3)`` colors in [0, 1] of surface points."""

CHARTS_PER_ATLAS = 128
"""xatlas grows each chart to at most 1/CHARTS_PER_ATLAS of the surface area, in one pass (no further chart
iterations). Its defaults (unbounded charts, one refining iteration) take over ten times as long on a 50k-face
marching-cubes mesh for the same atlas utilization. Unbounded charts on a smooth sphere take longest: a few huge charts to flatten.
A marching-cubes surface still splits into thousands of small charts (its normals vary), so the padding
between them decides how much of the texture the surface gets: 25 % of it with 4 texels, 39 % with 2."""


XATLAS_AREA_EPSILON = float(np.finfo(np.float32).eps)
"""xatlas leaves out of every chart each face whose area is at most this, in the input's own units (absolute,
not relative to the mesh): a mesh of small faces (a small object in scene units, a dense mesh) loses them all
and xatlas makes no atlas. `unwrap` therefore scales the mesh to a mean face area of 1 first; the UVs do not
depend on the scale, so only faces degenerate relative to the rest are left out."""


def unwrap(
    vertices: np.ndarray, faces: np.ndarray, size: int, padding: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """UV atlas of a triangle mesh for a ``size`` × ``size`` texture (xatlas: charts, parameterization, packing).

    vertices: (V, 3); faces: (F, 3). Charts are packed ``padding`` texels of xatlas's atlas apart — room for
    the seam padding, so bilinear lookups at an island's edge do not reach a neighbour. xatlas only
    approximates the resolution asked for (1024 → ~1440 on the sample), so in our texture the gaps are
    ~30 % narrower; it always packs one atlas (no texel density is given), whatever ``size``. Returns
    ``source (V2,) int64``: the input vertex each output vertex copies (vertices on a chart seam are split),
    ``faces (F, 3) int64`` into the output vertices (same order as the input faces) and ``uv (V2, 2) float64``
    in [0, 1]. Raises ValueError when no face has an area (an empty, collapsed or non-finite mesh).
    """
    verts = np.asarray(vertices, np.float64)
    tris = np.ascontiguousarray(faces, np.uint32)
    if len(tris) == 0:
        raise ValueError("cannot unwrap a mesh without faces")
    corners = verts[tris]  # (F, 3, 3)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite corners: their faces are not usable
        areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    usable = np.isfinite(areas) & (areas > 0)
    if not usable.any():
        raise ValueError(f"cannot unwrap the mesh: none of its {len(tris):,} faces has an area (all degenerate or non-finite)")
    used = np.unique(tris[usable])
    centre, mean_area = verts[used].mean(axis=0), float(areas[usable].mean())
    scaled = np.ascontiguousarray((verts - centre) / math.sqrt(mean_area), np.float32)  # mean face area 1
    scaled[~np.isfinite(scaled).all(axis=1)] = np.nan  # xatlas leaves out faces with a NaN corner (not with inf)
    max_chart_area = float(areas[usable].sum() / mean_area) / CHARTS_PER_ATLAS
    atlases, charts, source, new_faces, uv = in_child("xatlas_unwrap", scaled, tris, max_chart_area, int(size),
                                                      int(padding))
    if atlases != 1:
        left_out = int((areas[usable] / mean_area <= XATLAS_AREA_EPSILON).sum()) + int((~usable).sum())
        raise ValueError(f"xatlas made {atlases} atlases ({charts} charts) for a {size}² texture of "
                         f"{len(tris):,} faces, {left_out:,} of them degenerate")
    return np.asarray(source, np.int64), np.asarray(new_faces, np.int64), np.asarray(uv, np.float64)



def texel_samples(
    vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, normals: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface point and normal under every texel centre that a triangle covers in UV space.

    vertices, normals: (V, 3) (normals need not be unit; they are interpolated and normalised); faces (F, 3);
    uv: (V, 2) v up; size: texture (H, W). Returns ``mask (H, W) bool`` (covered texels, the islands),
    ``points (N, 3)`` and ``normals (N, 3)`` of the N covered texels in row-major order.
    """
    face_id, bary, _ = rasterize(uv_to_pixels(uv, size), None, faces, size)
    mask = face_id >= 0
    points = interpolate(vertices, faces, face_id, bary)[mask]
    nrm = interpolate(normals, faces, face_id, bary)[mask]
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return mask, points, nrm


def pad_texture(texture: np.ndarray, mask: np.ndarray, texels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dilate the islands: each texel outside ``mask`` within ``texels`` (Euclidean) of an island takes the
    color of the nearest island texel; ``texels=None`` fills the whole image.

    Why: a texel centre just outside every triangle still lies under the edge of one, so bilinear lookups
    and mipmaps (Blender's, a game engine's) at the seams read it; unpadded, seams show as dark lines.
    texture: (H, W, C); mask: (H, W) bool. Returns the padded texture and the mask of the texels it now
    defines (islands + padding).
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        return texture.copy(), mask.copy()
    dist, (rows, cols) = distance_transform_edt(~mask, return_indices=True)
    filled = mask | (dist <= (np.inf if texels is None else texels))
    out = texture.copy()
    out[filled] = texture[rows[filled], cols[filled]]
    return out, filled


def bake_texture(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    normals: np.ndarray,
    size: int,
    color_fn: ColorFn,
    pad: int | None = None,
    progress: Callable[[int], None] | None = None,
    chunk: int = 2**18,
) -> tuple[np.ndarray, np.ndarray]:
    """Texture (size, size, 3) uint8 of a UV-mapped mesh: ``color_fn`` at each covered texel's surface point
    (`texel_samples`), then `pad_texture` (``pad`` texels; None: all of the image).

    The same color function as for vertex colors gives the texture the same visibility test and robust
    average (e.g. `color.colors_from_photos` with a field fallback; give it a fixed depth tolerance: it is
    called on ``chunk`` texels at a time, each followed by ``progress(texels done in this call)``).
    Returns the texture and the island mask.
    """
    mask, points, nrm = texel_samples(vertices, faces, uv, normals, (size, size))
    colors = np.zeros((len(points), 3), np.float32)
    for s in range(0, len(points), chunk):
        colors[s : s + chunk] = np.clip(np.asarray(color_fn(points[s : s + chunk], nrm[s : s + chunk]), np.float32), 0.0, 1.0)
        if progress is not None:
            progress(len(colors[s : s + chunk]))
    texture = np.zeros((size, size, 3), np.float32)
    texture[mask] = colors
    texture, _ = pad_texture(texture, mask, pad)
    return np.round(texture * 255).astype(np.uint8), mask


@dataclass
class TexturedMesh:
    """A UV-mapped mesh and its texture (see the module docstring for the UV convention)."""

    vertices: np.ndarray
    """(V, 3) scene frame; vertices on chart seams appear once per chart."""
    faces: np.ndarray
    """(F, 3) int64 indices into vertices."""
    uv: np.ndarray
    """(V, 2) texture coordinates in [0, 1], v up."""
    normals: np.ndarray
    """(V, 3) outward unit normals of the mesh before its seams were split (continuous across seams)."""
    texture: np.ndarray
    """(S, S, 3) uint8 sRGB, padded."""
    mask: np.ndarray
    """(S, S) bool: the texels a triangle covers (the islands), before padding."""
    info: dict = field(default_factory=dict)
    """Faces before/after decimation, charts, coverage, timings."""


@dataclass
class UnwrappedMesh:
    """A decimated copy of a mesh with its UV atlas, before any colour: what `bake_unwrapped` textures. A step of its
    own so the unwrap (xatlas, seconds, in a process of its own) can run while the caller does other work."""

    vertices: np.ndarray
    """(V, 3); vertices on chart seams appear once per chart."""
    faces: np.ndarray
    """(F, 3) int64 indices into vertices."""
    uv: np.ndarray
    """(V, 2) in [0, 1], v up."""
    normals: np.ndarray
    """(V, 3) outward unit normals of the decimated mesh before its seams were split."""
    faces_in: int
    """Faces of the mesh before decimation."""
    timings: dict[str, float]
    """decimate_s, unwrap_s."""


def unwrap_mesh(vertices: np.ndarray, faces: np.ndarray, target_faces: int, size: int, padding: int = 2) -> UnwrappedMesh:
    """Decimate (quadric, `clean.decimate`) to about ``target_faces`` and `unwrap` for a ``size``² texture.

    vertices: (V, 3); faces (F, 3) counter-clockwise from outside; padding: texels xatlas leaves between charts."""
    timings: dict[str, float] = {}
    t = time.perf_counter()
    mesh, _ = decimate(trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False), target_faces)
    normals = np.asarray(mesh.vertex_normals, np.float64)
    timings["decimate_s"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    source, tris, uv = unwrap(mesh.vertices, mesh.faces, size, padding)
    timings["unwrap_s"] = round(time.perf_counter() - t, 3)
    return UnwrappedMesh(np.asarray(mesh.vertices, np.float64)[source], tris, uv, normals[source], len(faces), timings)


def bake_unwrapped(
    unwrapped: UnwrappedMesh,
    size: int,
    color_fn: ColorFn,
    pad: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> TexturedMesh:
    """`bake_texture` of an `unwrap_mesh` result: the textured mesh. size: texture side in texels (the one unwrapped
    for); pad: texels of seam padding (None: fill the whole image); progress: called with the texels baked, chunk by
    chunk."""
    t = time.perf_counter()
    u = unwrapped
    texture, mask = bake_texture(u.vertices, u.faces, u.uv, u.normals, size, color_fn, pad, progress)
    timings = {**u.timings, "bake_s": round(time.perf_counter() - t, 3)}
    info = {"faces_in": u.faces_in, "faces": len(u.faces), "vertices": len(u.vertices),
            "texture_size": int(size), "texels_covered": int(mask.sum()), "coverage": round(float(mask.mean()), 4),
            "timings_s": timings}
    return TexturedMesh(u.vertices, u.faces, u.uv, u.normals, texture, mask, info)


def make_textured_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    target_faces: int,
    size: int,
    color_fn: ColorFn,
    padding: int = 2,
    pad: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> TexturedMesh:
    """`unwrap_mesh` then `bake_unwrapped`: decimated to about ``target_faces``, unwrapped, a ``size``² texture baked
    with color_fn (see those two for the arguments)."""
    return bake_unwrapped(unwrap_mesh(vertices, faces, target_faces, size, padding), size, color_fn, pad, progress)
