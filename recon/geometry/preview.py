"""A quick look at a colored mesh without OpenGL: rasterized, Lambert-shaded, from two sides.

The mesh stage writes `preview_front.png` and `preview_side.png` with it, and `preview_textured.png` (unlit) of
the textured mesh.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from recon.camera import look_at, project
from recon.geometry.raster import interpolate, rasterize, render_mesh
from recon.geometry.texture import TexturedMesh


def look_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3, 3) world→camera rotation rows (right, up, back) of a camera at (azimuth, elevation) around +Z,
    looking at the origin; azimuth 0 looks along +Y (the camera sits on -Y)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = np.array([-math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
    return look_at(eye, np.zeros(3))[:3, :3].T


def preview_camera(vertices: np.ndarray, size: int, azimuth_deg: float = 0.0,
                   elevation_deg: float = 20.0) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """OpenGL c2w (4, 4) and pinhole intrinsics (fx, fy, cx, cy) of a size×size preview: the camera sits at
    (azimuth, elevation) three bounding-box radii from the bbox centre, looking at it, and the focal length
    and principal point frame the mesh's projection with a 5 % margin on its longer side."""
    vertices = np.asarray(vertices, np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    eye = centre + 3.0 * max(radius, 1e-9) * look_rotation(azimuth_deg, elevation_deg)[2]  # the camera's back axis
    c2w = look_at(eye, centre)
    xy, _ = project(vertices, c2w, np.array([1.0, 1.0, 0.0, 0.0]))  # tangent-plane coordinates (y down)
    lo_xy, hi_xy = xy.min(axis=0), xy.max(axis=0)
    focal = size / (1.1 * max(float((hi_xy - lo_xy).max()), 1e-12))
    cx, cy = size / 2 - focal * 0.5 * (lo_xy + hi_xy)
    return c2w, (focal, focal, float(cx), float(cy))


def render_preview(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray,
    azimuth_deg: float = 0.0,
    elevation_deg: float = 20.0,
    size: int = 512,
    background: Sequence[float] = (1.0, 1.0, 1.0),
) -> np.ndarray:
    """Image (size, size, 3) uint8 of a vertex-colored mesh, for a quick look without OpenGL.

    Rasterized exactly (`raster.rasterize`: every pixel shows its nearest face, no gaps or back faces
    showing through, as a point splat left), colors and normals interpolated per pixel, shaded Lambert
    (ambient 0.35 + 0.65·max(n·l, 0), light from the upper left of the viewer). vertices (V, 3) scene frame
    (+Z up); faces (F, 3); colors (V, 3) in [0, 1]; the camera is `preview_camera`.
    """
    image = np.tile(np.asarray(background, np.float64), (size, size, 1))
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    if len(mesh.faces) == 0 or mesh.area <= 0:
        return np.round(image * 255).astype(np.uint8)
    c2w, intrinsics = preview_camera(mesh.vertices, size, azimuth_deg, elevation_deg)
    xy, depth = project(mesh.vertices, c2w, np.asarray(intrinsics))
    face_id, bary, _ = rasterize(xy, depth, mesh.faces, (size, size))
    hit = face_id >= 0
    col = interpolate(np.clip(np.asarray(colors, np.float64), 0, 1), mesh.faces, face_id, bary)[hit]
    nrm = interpolate(mesh.vertex_normals @ c2w[:3, :3], mesh.faces, face_id, bary)[hit]  # camera frame
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    light = np.array([-0.4, 0.5, 0.77])
    light /= np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.clip(nrm @ light, 0.0, None)
    image[hit] = np.clip(col * shade[:, None], 0, 1)
    return np.round(image * 255).astype(np.uint8)


def write_mesh_previews(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, folder: Path) -> list[str]:
    """preview_front.png (from -Y, 20° above) and preview_side.png (from +X) of the mesh, scene frame."""
    from PIL import Image

    names = []
    for name, az in (("preview_front.png", 0.0), ("preview_side.png", 90.0)):
        Image.fromarray(render_preview(vertices, faces, colors, azimuth_deg=az)).save(folder / name)
        names.append(name)
    return names


def preview_textured(textured: TexturedMesh, size: int = 512, azimuth_deg: float = 0.0, elevation_deg: float = 20.0) -> np.ndarray:
    """Unlit render (size, size, 3) in [0, 1] of the textured mesh on white, from `render_preview`'s camera
    (`preview_camera`; azimuth 0: from -Y, 20° up), the whole mesh in view."""
    c2w, intrinsics = preview_camera(textured.vertices, size, azimuth_deg, elevation_deg)
    rgb, _ = render_mesh(textured.vertices, textured.faces, c2w, intrinsics, (size, size),
                         uv=textured.uv, texture=textured.texture)
    return rgb
