"""A quick look at a colored mesh without OpenGL: a z-buffered, Lambert-shaded point splat from two sides.

The mesh stage writes `preview_front.png` and `preview_side.png` with it.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from recon.scene import look_at


def look_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3, 3) world→camera rotation rows (right, up, back) of a camera at (azimuth, elevation) around +Z,
    looking at the origin; azimuth 0 looks along +Y (the camera sits on -Y)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = np.array([-math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
    return look_at(eye, np.zeros(3))[:3, :3].T


def render_preview(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 20.0,
    size: int = 512,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    seed: int = 0,
) -> np.ndarray:
    """Orthographic image (size, size, 3) uint8 of a vertex-colored mesh, for a quick look without OpenGL.

    Points are sampled on the surface by area (≈ 6 per covered pixel), colored and normal-interpolated
    barycentrically, shaded Lambert (ambient 0.35 + 0.65·max(n·l, 0), light from the upper left of the
    viewer) and z-buffered: each pixel shows its nearest point. vertices (V, 3) scene frame (+Z up);
    faces (F, 3); colors (V, 3) in [0, 1]; the camera looks at the bbox centre from (azimuth, elevation).
    """
    bg = np.asarray(background, np.float64)
    image = np.tile(bg, (size, size, 1))
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    if len(mesh.faces) == 0 or mesh.area <= 0:
        return np.round(image * 255).astype(np.uint8)
    rot = look_rotation(azimuth_deg, elevation_deg)
    centre = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    cam_v = (mesh.vertices - centre) @ rot.T
    half = 1.1 * float(np.abs(cam_v[:, :2]).max())  # half the image width: 10 % margin
    pix = 2 * half / size
    # ~6 points per pixel of the visible half of the surface: a pixel stays empty with p ≈ e^-6
    n = int(min(4_000_000, max(20_000, 6 * mesh.area / pix**2 / 2)))
    rng = np.random.default_rng(seed)
    face = rng.choice(len(mesh.faces), size=n, p=mesh.area_faces / mesh.area_faces.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)  # uniform on each triangle
    tri = mesh.faces[face]
    pts = np.einsum("nk,nkc->nc", bary, cam_v[tri])
    col = np.einsum("nk,nkc->nc", bary, np.clip(np.asarray(colors, np.float64), 0, 1)[tri])
    nrm = np.einsum("nk,nkc->nc", bary, (mesh.vertex_normals @ rot.T)[tri])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    light = np.array([-0.4, 0.5, 0.77])
    light /= np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.clip(nrm @ light, 0.0, None)
    u = ((pts[:, 0] + half) / pix).astype(np.int64)
    v = ((half - pts[:, 1]) / pix).astype(np.int64)
    ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
    flat, depth = v[ok] * size + u[ok], -pts[ok, 2]  # camera looks down -Z: nearer = larger z
    order = np.lexsort((depth, flat))  # by pixel, nearest first
    first = order[np.r_[True, flat[order][1:] != flat[order][:-1]]]
    image.reshape(-1, 3)[flat[first]] = np.clip(col[ok][first] * shade[ok][first, None], 0, 1)
    return np.round(image * 255).astype(np.uint8)


def write_mesh_previews(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, folder: Path) -> list[str]:
    """preview_front.png (from -Y, 20° above) and preview_side.png (from +X) of the mesh, scene frame."""
    from PIL import Image

    names = []
    for name, az in (("preview_front.png", 0.0), ("preview_side.png", 90.0)):
        Image.fromarray(render_preview(vertices, faces, colors, azimuth_deg=az)).save(folder / name)
        names.append(name)
    return names
