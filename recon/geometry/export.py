"""Write the colored mesh as glTF binary (.glb), OBJ and PLY — atomically, in stated frames.

Frames: input vertices are in the normalized scene frame (+Z up). ``transform`` (4×4, e.g. the
inverse normalization similarity back to COLMAP's frame, or a scale to metres) is applied first;
then, with ``y_up=True``:
- ``mesh.glb``: rotated −90° about X, so scene +Z is glTF +Y (glTF 2.0 is +Y up, front +Z); Blender's
  glTF importer turns it back to +Z up.
- ``mesh.obj``: same +Y-up frame (Blender's OBJ importer also assumes +Y up, forward −Z).
- ``mesh.ply``: kept +Z up (the transformed scene frame): Blender's and MeshLab's PLY importers
  apply no axis change, so it opens upright in Z-up tools.
Colors: OBJ and PLY carry the input colors (sRGB, as photos are); glTF defines COLOR_0 as *linear*,
so the glb gets sRGB→linear converted colors, stored as float32 to keep dark tones from banding.
Textures (`export_textured_mesh`) are sRGB PNGs, as glTF's baseColorTexture and OBJ's map_Kd expect.
"""
from __future__ import annotations

import io
import json
import os
import struct
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from recon.atomic import write_bytes_atomic
from recon.errors import ReconError

# Rotation −90° about X: (x, y, z) → (x, z, −y); scene +Z up becomes +Y up.
Z_UP_TO_Y_UP = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], np.float64)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding, elementwise on values in [0, 1]."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def apply_transform(
    vertices: np.ndarray, faces: np.ndarray, transform: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Map vertices (V, 3) by a 4×4 affine; a mirroring transform (det < 0) also flips face winding
    so normals keep pointing outward."""
    t = np.asarray(transform, np.float64)
    if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]):
        raise ValueError(f"transform must be a 4x4 affine matrix with last row [0, 0, 0, 1], got {t.tolist()}")
    out = np.asarray(vertices, np.float64) @ t[:3, :3].T + t[:3, 3]
    return out, (faces[:, ::-1] if np.linalg.det(t[:3, :3]) < 0 else faces)


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


def export_record(frame: str, why: str, transform: np.ndarray | None, paths: dict[str, Path]) -> dict:
    """The mesh report's "export": the frame and why (`export_transform`), the transform `export_mesh` applied, the
    files it wrote and each one's axes."""
    return {
        "frame": frame,
        "reason": why,
        "transform": (transform if transform is not None else np.eye(4)).tolist(),
        "transform_note": "maps the normalized scene frame (+Z up) to the exported frame, before the up-axis change",
        "files": {k: p.name for k, p in paths.items()},
        "axes": {"glb": "+Y up (scene +Z rotated -90° about X)", "obj": "+Y up", "ply": "+Z up (the exported frame itself)"},
    }


def glb_bytes(
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    colors_linear: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    png: bytes | None = None,
    material: str = "vertex_color",
) -> bytes:
    """Minimal glTF 2.0 binary: one mesh, POSITION/NORMAL (float32 VEC3), COLOR_0 (float32 VEC3, linear) when
    ``colors_linear`` is given, TEXCOORD_0 when ``uv`` (V, 2; OBJ convention, v up: flipped here to glTF's v down)
    and ``png`` (the encoded texture, embedded as it is: encoded once for the .png file and the .glb) are; uint32
    indices; a dielectric material (metallic 0, rough 1) so vertex colors or the texture show as they are."""
    arrays = [np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(normals, np.float32)]
    attributes = {"POSITION": 0, "NORMAL": 1}
    if colors_linear is not None:
        attributes["COLOR_0"] = len(arrays)
        arrays.append(np.ascontiguousarray(colors_linear, np.float32))
    if uv is not None:
        attributes["TEXCOORD_0"] = len(arrays)
        flipped = np.asarray(uv, np.float64) * [1.0, -1.0] + [0.0, 1.0]
        arrays.append(np.ascontiguousarray(flipped, np.float32))
    indices = len(arrays)
    arrays.append(np.ascontiguousarray(faces, np.uint32).reshape(-1))
    views, accessors, chunks, offset = [], [], [], 0
    for i, arr in enumerate(arrays):  # every array is 4-byte elements, so views stay 4-byte aligned
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": arr.nbytes,
                      "target": 34963 if i == indices else 34962})
        acc = {"bufferView": i, "componentType": 5125 if i == indices else 5126, "count": int(arr.shape[0]),
               "type": "SCALAR" if i == indices else ("VEC2" if arr.shape[1] == 2 else "VEC3")}
        if i == 0:  # POSITION requires min/max
            acc["min"], acc["max"] = arr.min(axis=0).tolist(), arr.max(axis=0).tolist()
        accessors.append(acc)
        chunks.append(arr.tobytes())
        offset += arr.nbytes
    pbr: dict = {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": 1.0}
    doc: dict = {
        "asset": {"version": "2.0", "generator": "recon"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "mesh"}],
        "meshes": [{"name": "mesh", "primitives": [{
            "attributes": attributes, "indices": indices, "material": 0, "mode": 4}]}],
        "materials": [{"name": material, "pbrMetallicRoughness": pbr}],
        "accessors": accessors,
        "bufferViews": views,
    }
    if png is not None:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(png)})
        chunks.append(png + b"\0" * (-len(png) % 4))
        offset += len(chunks[-1])
        doc["images"] = [{"bufferView": len(views) - 1, "mimeType": "image/png"}]
        doc["textures"] = [{"source": 0}]
        pbr["baseColorTexture"] = {"index": 0}
    doc["buffers"] = [{"byteLength": offset}]
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(chunks)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(js), b"JSON"), js,
        struct.pack("<I4s", len(binary), b"BIN\0"), binary,
    ])


def obj_text(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> str:
    """Wavefront OBJ with per-vertex colors as ``v x y z r g b`` (r, g, b in [0, 1]); 1-based faces.

    One %-format of a repeated line over all the numbers: four times faster than a format call a line."""
    v = np.hstack([np.asarray(vertices, np.float64), np.clip(colors, 0, 1)])
    f = np.asarray(faces, np.int64).reshape(-1, 3) + 1
    return ("# recon mesh: vertex colors as 'v x y z r g b'\n"
            + ("v %.7g %.7g %.7g %.4f %.4f %.4f\n" * len(v)) % tuple(v.ravel().tolist())
            + ("f %d %d %d\n" * len(f)) % tuple(f.ravel().tolist()))


def textured_obj_text(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, normals: np.ndarray, mtl_file: str,
                      material: str) -> str:
    """Wavefront OBJ of a UV-mapped mesh using material ``material`` of ``mtl_file``: ``v``, ``vt`` (v up) and ``vn``
    lines, one each per vertex, and faces ``f a/a/a b/b/b c/c/c`` (1-based); formatted as `obj_text` is."""
    f = np.repeat(np.asarray(faces, np.int64).reshape(-1, 3) + 1, 3, axis=1)
    return (f"# recon textured mesh\nmtllib {mtl_file}\nusemtl {material}\n"
            + ("v %.8g %.8g %.8g\n" * len(vertices)) % tuple(np.asarray(vertices, np.float64).ravel().tolist())
            + ("vt %.8g %.8g\n" * len(uv)) % tuple(np.asarray(uv, np.float64).ravel().tolist())
            + ("vn %.6g %.6g %.6g\n" * len(normals)) % tuple(np.asarray(normals, np.float64).ravel().tolist())
            + ("f %d/%d/%d %d/%d/%d %d/%d/%d\n" * len(f)) % tuple(f.ravel().tolist()))


def export_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray,
    out_dir: str | os.PathLike,
    stem: str = "mesh",
    transform: np.ndarray | None = None,
    y_up: bool = True,
) -> dict[str, Path]:
    """Write ``{stem}.glb``, ``{stem}.obj`` and ``{stem}.ply`` into out_dir; returns their paths by format.

    vertices: (V, 3) scene frame (+Z up); faces: (F, 3) counter-clockwise from outside; colors:
    (V, 3) float sRGB in [0, 1]; transform: optional (4, 4) scene → output frame, applied before the
    up-axis change (see the module docstring for each file's frame).
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    colors = np.clip(np.asarray(colors, np.float64), 0.0, 1.0)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or colors.shape != vertices.shape:
        raise ValueError(f"need vertices (V, 3) and colors (V, 3); got {vertices.shape}, {colors.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and (faces.min() < 0 or faces.max() >= len(vertices))):
        raise ValueError(f"faces must be (F, 3) indices into {len(vertices)} vertices")
    if transform is not None:
        vertices, faces = apply_transform(vertices, faces, transform)
    up = apply_transform(vertices, faces, Z_UP_TO_Y_UP)[0] if y_up else vertices
    mesh_up = trimesh.Trimesh(up, faces, process=False)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "glb": write_bytes_atomic(out / f"{stem}.glb",
                             glb_bytes(up, faces, mesh_up.vertex_normals, srgb_to_linear(colors))),
        "obj": write_bytes_atomic(out / f"{stem}.obj", obj_text(up, faces, colors)),
    }
    rgba = np.hstack([np.round(colors * 255), np.full((len(colors), 1), 255)]).astype(np.uint8)
    ply = trimesh.Trimesh(vertices, faces, vertex_colors=rgba, process=False)
    paths["ply"] = write_bytes_atomic(out / f"{stem}.ply", ply.export(file_type="ply", encoding="binary"))
    return paths


def mtl_text(name: str, texture_file: str) -> str:
    """An OBJ material whose diffuse color is the texture alone (Kd 1, no specular), so importers show
    the image as it is."""
    return (f"# recon textured mesh\nnewmtl {name}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 0\nillum 1\n"
            f"map_Kd {texture_file}\n")


def export_textured_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    texture: np.ndarray,
    out_dir: str | os.PathLike,
    stem: str = "mesh_textured",
    normals: np.ndarray | None = None,
    transform: np.ndarray | None = None,
    y_up: bool = True,
) -> dict[str, Path]:
    """Write ``{stem}.glb`` (baseColorTexture embedded) and ``{stem}.obj`` + ``.mtl`` + ``.png``; returns
    their paths by format.

    vertices: (V, 3) scene frame (+Z up); faces (F, 3) counter-clockwise from outside; uv: (V, 2) in
    [0, 1], v up (OBJ/OpenGL; flipped for glTF); texture: (H, W, 3) uint8 sRGB, top row first;
    normals: optional (V, 3) outward (e.g. of the mesh before its seams were split, so shading does not
    break at them), else computed from the faces; transform and y_up as in `export_mesh`. The material is
    metallic 0, roughness 1, so Blender's glTF importer shows the texture through an Image Texture node
    with no node work. The OBJ is written last: a reader never finds it before its material and image.
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    uv, texture = np.asarray(uv, np.float64), np.asarray(texture)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or uv.shape != (len(vertices), 2):
        raise ValueError(f"need vertices (V, 3) and uv (V, 2); got {vertices.shape}, {uv.shape}")
    if texture.dtype != np.uint8 or texture.ndim != 3 or texture.shape[2] != 3:
        raise ValueError(f"texture must be (H, W, 3) uint8, got {texture.shape} {texture.dtype}")
    linear = np.eye(3)
    for t in ([transform] if transform is not None else []) + ([Z_UP_TO_Y_UP] if y_up else []):
        vertices, faces = apply_transform(vertices, faces, t)
        linear = np.asarray(t, np.float64)[:3, :3] @ linear
    if normals is not None:  # normals map by the inverse transpose of the linear part
        n = np.asarray(normals, np.float64) @ np.linalg.inv(linear)
    else:
        n = np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    png = io.BytesIO()
    Image.fromarray(texture).save(png, format="PNG")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "glb": write_bytes_atomic(out / f"{stem}.glb", glb_bytes(vertices, faces, n, uv=uv, png=png.getvalue(),
                                                                 material=stem)),
        "png": write_bytes_atomic(out / f"{stem}.png", png.getvalue()),
        "mtl": write_bytes_atomic(out / f"{stem}.mtl", mtl_text(stem, f"{stem}.png")),
    }
    obj = textured_obj_text(vertices, faces, uv, n, f"{stem}.mtl", stem)
    paths["obj"] = write_bytes_atomic(out / f"{stem}.obj", obj)
    return paths
