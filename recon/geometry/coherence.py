"""Is a mesh of a real capture one coherent surface that covers what the photos show? Two numbers say it.

* **largest piece**: the share of the mesh's surface area held by its largest face-connected piece. A mesh of
  one object is near 1; scattered fragments of a room (or a torn object) are far below.
* **projected coverage**: the mesh rasterized into the photos' cameras (`geometry.raster`) against the object
  pixels of each photo: the fraction of object pixels the mesh covers (what the photos see that the mesh has),
  and the fraction of mesh pixels outside the object (what the mesh has that is not the object).
  The object pixels come from the masks when the capture has them; without masks from the field: the pixels
  whose rendered depth puts their surface point inside the object region (the box the mesh was cut to, above
  the ground plane it was cut at), i.e. what the photos show of the object.
* **point agreement**: the SfM points each photo observes against the mesh's z-buffer in that photo. A photo saw a
  surface at each of its points, so the mesh should pass through them: the share of sightings where it does
  (`on`), where it lies in front and hides the point (`in_front`: mesh floating before a seen surface, such as
  sceaux_castle's roofs smeared towards the cameras) and where it is behind or absent (`missing`). It needs no
  field, so it also checks what the projected coverage takes from the field's depth.

There is no ground truth on a real capture; these are the checks that still can fail there.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import trimesh

from recon.camera import image_rays, project
from recon.geometry.clean import component_areas
from recon.geometry.raster import mesh_depth, per_camera

__all__ = ["largest_piece", "depth_points", "object_pixels", "mesh_zbuffers", "projected_coverage", "point_agreement"]


def largest_piece(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Face-connected pieces of the mesh: how many, and the largest one's share of the total area (0 for an empty mesh)."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    if len(mesh.faces) == 0 or mesh.area <= 0:
        return {"pieces": 0, "largest_area_fraction": 0.0}
    _, areas = component_areas(mesh)
    return {"pieces": int(len(areas)), "largest_area_fraction": float(areas.max() / areas.sum())}


def depth_points(c2w: np.ndarray, intrinsics: Sequence[float], depth: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) at distance ``depth`` (H, W) along the unit rays through the pixel centres of an
    OpenGL camera (`recon.camera.image_rays`, the rays the fields render their depth along)."""
    h, w = depth.shape
    o, d = image_rays(np.asarray(c2w, np.float64), *(float(v) for v in intrinsics), w, h)
    return o + d * np.asarray(depth, np.float64)[..., None]


def object_pixels(
    c2w: np.ndarray, intrinsics: Sequence[float], depth: np.ndarray, inside: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray:
    """Bool (H, W): pixels whose surface point (rendered ray distance ``depth``) ``inside(points (N, 3)) -> (N,)``
    calls object. Pixels the field leaves transparent read the far distance and fall outside any object region."""
    pts = depth_points(c2w, intrinsics, depth).reshape(-1, 3)
    ok = np.isfinite(pts).all(axis=1)
    out = np.zeros(len(pts), bool)
    out[ok] = np.asarray(inside(pts[ok]), bool)
    return out.reshape(depth.shape)


def mesh_zbuffers(
    vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[tuple[np.ndarray, Sequence[float], tuple[int, int]]]
) -> list[np.ndarray]:
    """The mesh's z-buffer (H, W) in each camera (c2w (4, 4) OpenGL, (fx, fy, cx, cy), (H, W)), inf where no face
    covers a pixel (`raster.mesh_depth`): what `projected_coverage` and `point_agreement` read."""
    verts = np.asarray(vertices, np.float64)
    tri = np.asarray(faces, np.int64).reshape(-1, 3)
    return per_camera(lambda cam: mesh_depth(verts, tri, cam[0], cam[1], tuple(cam[2])), cameras)


def projected_coverage(zbuffers: Sequence[np.ndarray], objects: Sequence[np.ndarray]) -> dict:
    """The mesh, as its z-buffer in each camera (`mesh_zbuffers`), against that view's object pixels
    ``objects[k]`` (H, W) bool.

    Returns ``coverage``: covered object pixels / object pixels over all views; ``outside``: mesh pixels that are
    not object / mesh pixels; both per view too, and the pixel counts. A view without object pixels counts in
    ``outside`` only.
    """
    if len(zbuffers) != len(objects):
        raise ValueError(f"one object mask per camera: {len(zbuffers)} cameras, {len(objects)} masks")
    per_view = []
    obj_total = covered_total = mesh_total = outside_total = 0
    for zbuf, obj in zip(zbuffers, objects):
        obj = np.asarray(obj, bool)
        if obj.shape != zbuf.shape:
            raise ValueError(f"object mask {obj.shape} does not match the camera's size {zbuf.shape}")
        mesh_px = np.isfinite(zbuf)
        n_obj, n_cov = int(obj.sum()), int((mesh_px & obj).sum())
        n_mesh, n_out = int(mesh_px.sum()), int((mesh_px & ~obj).sum())
        obj_total += n_obj
        covered_total += n_cov
        mesh_total += n_mesh
        outside_total += n_out
        per_view.append({"object_pixels": n_obj, "coverage": n_cov / n_obj if n_obj else None,
                         "outside": n_out / n_mesh if n_mesh else None})
    return {
        "coverage": covered_total / obj_total if obj_total else 0.0,
        "outside": outside_total / mesh_total if mesh_total else 0.0,
        "object_pixels": obj_total,
        "mesh_pixels": mesh_total,
        "views": per_view,
    }


def point_agreement(
    zbuffers: Sequence[np.ndarray],
    cameras: Sequence[tuple[np.ndarray, Sequence[float], tuple[int, int]]],
    points: Sequence[np.ndarray],
    tolerance: float,
) -> dict:
    """Each camera's observed points ``points[k]`` (N_k, 3) against the mesh's z-buffer in that camera
    (`mesh_zbuffers`; module docstring): a sighting is ``on`` when the nearest mesh face at the point's pixel lies
    within ``tolerance`` (scene units, along the optical axis) of it, ``in_front`` when nearer than that, else
    ``missing``. Points behind a camera or outside its image are not sightings. Returns the three shares, the
    number of sightings and the tolerance."""
    if not len(zbuffers) == len(cameras) == len(points):
        raise ValueError(f"one point set per camera: {len(cameras)} cameras, {len(points)} point sets")
    on = in_front = total = 0
    for zbuf, (c2w, intr, _), pts in zip(zbuffers, cameras, points):
        uv, depth = project(np.asarray(pts, np.float64).reshape(-1, 3), np.asarray(c2w, np.float64),
                            np.asarray(intr, np.float64))
        h, w = zbuf.shape
        ok = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        gap = zbuf[uv[ok, 1].astype(int), uv[ok, 0].astype(int)] - depth[ok]  # inf where no face covers the pixel
        on += int((np.abs(gap) <= tolerance).sum())
        in_front += int((gap < -tolerance).sum())
        total += int(ok.sum())
    shares = ({"on": on / total, "in_front": in_front / total, "missing": (total - on - in_front) / total} if total
              else {"on": 0.0, "in_front": 0.0, "missing": 0.0})
    return {"sightings": total, **shares, "tolerance": float(tolerance)}
