"""A small z-buffered triangle rasterizer in numpy: meshes into camera views, and UV layouts into texels.

Why here: to measure a mesh against the photos (render it into the held-out views, PSNR) and to find the
3D point under each texel of a texture atlas, without OpenGL. It is exact at pixel centres: pixel (i, j)
covers [i, i+1) × [j, j+1) and is sampled at (i + 0.5, j + 0.5), the convention of `geometry.color`.

A pixel belongs to a triangle when its centre lies inside or on an edge (edge functions ≥ 0 after
orienting the triangle); a pixel on an edge two triangles share goes to the nearer one, or to either
at equal depth. Barycentric weights are perspective-correct: screen-space weights b_i divided by each
vertex's depth w_i and renormalised (b_i/w_i / Σ b_j/w_j), and the depth is 1 / Σ b_j/w_j.
Triangles with a vertex at or behind ``near`` are dropped, not clipped (the cameras we render from are
outside the object).
"""
from __future__ import annotations

import ctypes
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path
from typing import Sequence, TypeVar

import numpy as np

from recon.camera import project
from recon.geometry.color import sample_bilinear

CANDIDATES_PER_CHUNK = 2**22
"""Pixel-triangle candidates (bounding-box pixels) tested at once: bounds memory to a few hundred MB."""

T = TypeVar("T")
R = TypeVar("R")


@lru_cache(maxsize=1)
def native_rasterizer() -> ctypes.CDLL | None:
    """raster.c built and loaded (the same z-buffer, a face at a time), or None: the numpy code then runs. Without
    a C compiler, or with RECON_NATIVE=0, nothing changes but the time."""
    from recon.nerf.native import load_c_library

    lib, _ = load_c_library(Path(__file__).with_name("raster.c"))
    if lib is not None:
        p, i64 = ctypes.c_void_p, ctypes.c_int64
        lib.recon_rasterize.restype = None
        lib.recon_rasterize.argtypes = [i64, p, p, p, i64, i64, p, p, p]
    return lib


def rasterize(
    xy: np.ndarray, w: np.ndarray | None, faces: np.ndarray, hw: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffered coverage of triangles on an H×W pixel grid.

    xy: (V, 2) continuous pixel coordinates (x right, y down); w: (V,) positive depth along the optical axis
    (nearer wins, and weights are perspective-corrected by it) or None for a flat layout (UV space: all at
    depth 1); faces: (F, 3) vertex indices; hw: (H, W).
    Returns ``face_id (H, W) int64`` (-1 where empty), ``bary (H, W, 3) float64`` perspective-correct
    weights of the face's three vertices (0 where empty) and ``depth (H, W) float64`` (inf where empty).
    """
    h, w_img = hw
    xy = np.ascontiguousarray(xy, np.float64)
    faces = np.ascontiguousarray(faces, np.int64).reshape(-1, 3)
    depth_v = None if w is None else np.ascontiguousarray(w, np.float64)
    face_id = np.full(h * w_img, -1, np.int64)
    bary = np.zeros((h * w_img, 3))
    zbuf = np.full(h * w_img, np.inf)
    if len(faces) == 0:
        return face_id.reshape(h, w_img), bary.reshape(h, w_img, 3), zbuf.reshape(h, w_img)
    if xy.ndim != 2 or xy.shape[1] != 2 or (depth_v is not None and depth_v.shape != (len(xy),)):
        raise ValueError(f"rasterize needs xy (V, 2) and w (V,) or None; got {xy.shape} and "
                         f"{None if depth_v is None else depth_v.shape}")
    if faces.min() < 0 or faces.max() >= len(xy):  # the C code would read past the vertices
        raise IndexError(f"faces index vertices {faces.min()}..{faces.max()} of {len(xy)}")
    lib = native_rasterizer()
    if lib is not None:
        lib.recon_rasterize(len(faces), faces.ctypes.data, xy.ctypes.data, None if depth_v is None else depth_v.ctypes.data,
                            w_img, h, face_id.ctypes.data, bary.ctypes.data, zbuf.ctypes.data)
        return face_id.reshape(h, w_img), bary.reshape(h, w_img, 3), zbuf.reshape(h, w_img)
    if depth_v is None:
        depth_v = np.ones(len(xy))

    tri = xy[faces]  # (F, 3, 2)
    tri_w = depth_v[faces]  # (F, 3)
    area = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
            - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0]))
    # pixel centres c + 0.5 inside the triangle's bounds: c in [ceil(min - 0.5), floor(max - 0.5)]
    # (minima of the three corners taken pairwise: numpy's reductions over a short middle axis are ~10x slower)
    # (clipped to the image before they become integers, as in raster.c)
    lo = np.maximum(np.ceil(np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2]) - 0.5), 0.0)
    hi = np.minimum(np.floor(np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2]) - 0.5), [w_img - 1, h - 1])
    nearest = np.minimum(np.minimum(tri_w[:, 0], tri_w[:, 1]), tri_w[:, 2])
    finite = np.isfinite(tri).all(axis=(1, 2)) & np.isfinite(tri_w).all(axis=1)  # faces with a non-finite corner: none
    keep = finite & (np.abs(area) > 1e-12) & (nearest > 1e-9) & (hi[:, 0] >= lo[:, 0]) & (hi[:, 1] >= lo[:, 1])
    lo, hi = (np.where(keep[:, None], b, 0.0).astype(np.int64) for b in (lo, hi))
    ids = np.flatnonzero(keep)
    if len(ids) == 0:
        return face_id.reshape(h, w_img), bary.reshape(h, w_img, 3), zbuf.reshape(h, w_img)
    span = hi[ids] - lo[ids] + 1  # (n, 2) bounding-box width, height in pixels
    count = span[:, 0] * span[:, 1]
    ends = np.cumsum(count)
    start = 0
    while start < len(ids):  # chunks of faces with at most CANDIDATES_PER_CHUNK bbox pixels (at least one face)
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + CANDIDATES_PER_CHUNK, side="right")))
        _raster_chunk(ids[start:stop], lo[ids[start:stop]], span[start:stop], count[start:stop],
                      tri, tri_w, area, w_img, face_id, bary, zbuf)
        start = stop
    return face_id.reshape(h, w_img), bary.reshape(h, w_img, 3), zbuf.reshape(h, w_img)


def _raster_chunk(
    ids: np.ndarray, lo: np.ndarray, span: np.ndarray, count: np.ndarray, tri: np.ndarray, tri_w: np.ndarray,
    area: np.ndarray, width: int, face_id: np.ndarray, bary: np.ndarray, zbuf: np.ndarray,
) -> None:
    """Test every bounding-box pixel of faces ``ids`` and merge the nearer hits into the flat buffers."""
    f = np.repeat(np.arange(len(ids)), count)  # candidate → position in ids
    local = np.arange(len(f)) - np.repeat(np.cumsum(count) - count, count)
    px = lo[f, 0] + local % span[f, 0]
    py = lo[f, 1] + local // span[f, 0]
    fid = ids[f]
    t = tri[fid]  # (n, 3, 2)
    cx, cy = px + 0.5, py + 0.5
    # edge functions: weight of vertex i is the signed area of (p, v_{i+1}, v_{i+2}) over the triangle's
    b = np.empty((len(f), 3))
    for i in range(3):
        a, c = t[:, (i + 1) % 3], t[:, (i + 2) % 3]
        b[:, i] = (a[:, 0] - cx) * (c[:, 1] - cy) - (a[:, 1] - cy) * (c[:, 0] - cx)
    b /= area[fid, None]
    inside = np.all(b >= -1e-12, axis=1)
    if not inside.any():
        return
    b, fid, pix = b[inside], fid[inside], py[inside] * width + px[inside]
    inv_w = b / tri_w[fid]  # (n, 3) b_i / w_i
    s = inv_w.sum(axis=1)
    depth = 1.0 / s
    order = np.lexsort((depth, pix))  # by pixel, nearest first
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]]
    pix, depth = pix[first], depth[first]
    nearer = depth < zbuf[pix]
    pix = pix[nearer]
    zbuf[pix] = depth[nearer]
    face_id[pix] = fid[first][nearer]
    bary[pix] = (inv_w[first] / s[first, None])[nearer]


def interpolate(attr: np.ndarray, faces: np.ndarray, face_id: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Per-pixel attribute (H, W, C) from per-vertex ``attr`` (V, C) of the covering face, weighted by
    ``bary``; 0 where face_id is -1. faces (F, 3) index attr's rows."""
    attr = np.asarray(attr, np.float64)
    out = np.zeros((*face_id.shape, attr.shape[1]))
    hit = face_id >= 0
    corners = attr[np.asarray(faces, np.int64)[face_id[hit]]]  # (n, 3, C)
    out[hit] = np.einsum("nk,nkc->nc", bary[hit], corners)
    return out


def uv_to_pixels(uv: np.ndarray, size: Sequence[int]) -> np.ndarray:
    """Texture coordinates (N, 2), OpenGL/OBJ convention (u right, v up, origin bottom-left) → continuous
    pixel coordinates of an (H, W) image stored top row first: x = u·W, y = (1 − v)·H."""
    h, w = size
    uv = np.asarray(uv, np.float64)
    return np.stack([uv[:, 0] * w, (1.0 - uv[:, 1]) * h], axis=1)


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    c2w: np.ndarray,
    intrinsics: Sequence[float],
    hw: tuple[int, int],
    colors: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    texture: np.ndarray | None = None,
    background: Sequence[float] = (1.0, 1.0, 1.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Unlit render of a vertex-colored or textured mesh into a pinhole camera: the colors as they are
    (what the photos show), so it compares to a photo directly.

    vertices: (V, 3) scene frame; faces: (F, 3); c2w: (4, 4) OpenGL (looks down -Z); intrinsics fx, fy,
    cx, cy in pixels; hw: (H, W). Give ``colors`` (V, 3) in [0, 1] (interpolated barycentrically), or
    ``uv`` (V, 2, v up) with ``texture`` (Th, Tw, 3) float [0, 1] or uint8 (sampled bilinearly at the
    perspective-correct UV). Returns ``rgb (H, W, 3) float64`` (background where empty) and
    ``mask (H, W) bool`` (covered pixels).
    """
    if (colors is None) == (texture is None or uv is None):
        raise ValueError("render_mesh needs either colors or (uv and texture)")
    xy, z = project(np.asarray(vertices, np.float64), np.asarray(c2w, np.float64), np.asarray(intrinsics, np.float64))
    face_id, bary, _ = rasterize(xy, z, faces, hw)
    mask = face_id >= 0
    rgb = np.tile(np.asarray(background, np.float64)[:3], (*hw, 1))
    if colors is not None:
        rgb[mask] = interpolate(colors, faces, face_id, bary)[mask]
    else:
        tex = np.asarray(texture)
        scale = 1 / 255 if tex.dtype == np.uint8 else 1.0
        at = interpolate(uv, faces, face_id, bary)[mask]
        rgb[mask] = sample_bilinear(tex, uv_to_pixels(at, tex.shape[:2]))[:, :3] * scale
    return np.clip(rgb, 0.0, 1.0), mask


def per_camera(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(item) for item in items]`` on a thread per core (`cpu_threads`: a Ray task's share) when the C
    rasterizer is loaded (its calls let go of the GIL, so a mesh rasterized into many cameras takes a fraction of the
    time), results in order. The numpy fallback takes them one at a time: each of its calls already holds a few
    hundred MB (CANDIDATES_PER_CHUNK)."""
    from recon.nerf.device import cpu_threads

    workers = min(len(items), cpu_threads()) if native_rasterizer() is not None else 1
    if workers <= 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="recon-raster") as pool:
        return list(pool.map(fn, items))


def mesh_depth(
    vertices: np.ndarray, faces: np.ndarray, c2w: np.ndarray, intrinsics: Sequence[float], hw: tuple[int, int]
) -> np.ndarray:
    """The mesh's own z-buffer (H, W) in a pinhole camera: depth along the optical axis of the nearest face at each
    pixel centre, inf where no face covers it. Colour baking tests a surface point against it (depth_kind "z"):
    a point is seen when nothing of the mesh lies in front of it, which a field's rendered depth only approximates
    (its expected depth sits behind the iso-surface by an amount that depends on the level and the field's softness)."""
    xy, z = project(np.asarray(vertices, np.float64), np.asarray(c2w, np.float64), np.asarray(intrinsics, np.float64))
    return rasterize(xy, z, faces, hw)[2]
