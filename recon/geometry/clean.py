"""Mesh clean-up after marching cubes: crop, drop floaters and hidden walls, smooth, decimate — with a report of each step.

All arrays are in the normalized scene frame (+Z up); nothing here reads or writes files.
"""
from __future__ import annotations

from typing import Callable

import fast_simplification
import numpy as np
import trimesh
from trimesh import graph, smoothing

SeenFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``seen_fn(vertices (V, 3), outward normals (V, 3)) -> (V,)`` how many photos see each vertex (0: none)."""


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """Trimesh that merges duplicate vertices and drops the faces that merging collapsed (a repeated vertex) and
    unused vertices. Zero-area faces with three distinct vertices stay: marching cubes leaves some, and dropping
    one opens a three-edge hole (a surface-model bowl's zero set came out not watertight that way)."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=True)
    f = mesh.faces
    mesh.update_faces((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    mesh.remove_unreferenced_vertices()
    return mesh


def _counts(mesh: trimesh.Trimesh) -> dict:
    return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces))}


def crop_to_aabb(mesh: trimesh.Trimesh, aabb: np.ndarray, eps: float = 1e-6) -> trimesh.Trimesh:
    """Keep faces whose three vertices lie inside aabb (2, 3) (scene units, ``eps`` slack)."""
    box = np.asarray(aabb, np.float64)
    inside = np.all((mesh.vertices >= box[0] - eps) & (mesh.vertices <= box[1] + eps), axis=1)
    out = mesh.copy()
    out.update_faces(inside[mesh.faces].all(axis=1))
    out.remove_unreferenced_vertices()
    return out


def cut_below_plane(mesh: trimesh.Trimesh, plane: np.ndarray, margin: float) -> tuple[trimesh.Trimesh, int]:
    """Drop faces with a vertex less than ``margin`` above the plane (nx, ny, nz, d), n·x = d, n unit and
    pointing up: the ground an object stands on. Returns the mesh and how many faces went."""
    plane = np.asarray(plane, np.float64)
    above = mesh.vertices @ plane[:3] - plane[3] >= margin
    keep = above[mesh.faces].all(axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out, int((~keep).sum())


def keep_vertices(mesh: trimesh.Trimesh, keep_fn: Callable[[np.ndarray], np.ndarray]) -> tuple[trimesh.Trimesh, int]:
    """Drop faces with a vertex for which ``keep_fn(vertices (V, 3)) -> (V,) bool`` is False."""
    keep = np.asarray(keep_fn(np.asarray(mesh.vertices)), bool)[mesh.faces].all(axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out, int((~keep).sum())


def component_areas(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Face-connected components: labels (F,) and surface area of each component (C,) in scene units²."""
    labels = graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    areas = np.bincount(labels, weights=mesh.area_faces, minlength=labels.max(initial=-1) + 1)
    return labels, areas


def remove_small_components(mesh: trimesh.Trimesh, min_fraction: float) -> tuple[trimesh.Trimesh, dict]:
    """Drop components whose area is below ``min_fraction`` × the largest component's area.

    Area, not face count, so the rule does not depend on how finely a piece was triangulated.
    """
    if len(mesh.faces) == 0:
        return mesh, {"components": 0, "removed": 0, "kept": 0, "rule": "empty mesh"}
    labels, areas = component_areas(mesh)
    keep = areas >= min_fraction * areas.max()
    out = mesh.copy()
    out.update_faces(keep[labels])
    out.remove_unreferenced_vertices()
    rule = f"keep components with area >= {min_fraction:g} x largest ({areas.max():.4g} units^2)"
    return out, {"components": int(len(areas)), "removed": int((~keep).sum()), "kept": int(keep.sum()), "rule": rule,
                 "removed_area": float(areas[~keep].sum())}


def remove_hidden_faces(mesh: trimesh.Trimesh, seen_fn: SeenFn) -> tuple[trimesh.Trimesh, dict]:
    """Drop faces none of whose vertices any photo sees (``seen_fn(vertices, normals)``).

    Why: a radiance field only has to be opaque where the photos look. Inside the object it is
    unconstrained: a fast field is typically a shell a few voxels thick with a soft, noisy inside, and
    marching cubes turns that inside into walls and islands behind the visible surface. Depth-tested
    visibility removes them whatever the iso-level, so the level can be low enough to close the shell.
    """
    seen = np.asarray(seen_fn(mesh.vertices, mesh.vertex_normals)) > 0
    keep = seen[mesh.faces].any(axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    return out, {"removed_faces": int((~keep).sum()), "removed_area": float(mesh.area_faces[~keep].sum()),
                 "rule": "drop faces with no vertex that any photo sees (facing it, at the field's rendered depth)"}


def remove_duplicate_faces(faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Faces (F, 3) on the same three vertices: opposite windings cancel in pairs (a zero-volume fin,
    which edge collapse occasionally leaves and which makes the edges non-manifold); of several with
    the same winding one is kept. Returns the remaining faces (order kept) and how many were removed."""
    if len(faces) == 0:
        return faces, 0
    order = np.argsort(faces, axis=1)
    even = ((order[:, 1] - order[:, 0]) % 3) == 1  # (a, b, c) is a rotation of its sorted order
    _, group = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True)
    group = group.ravel()
    n_even = np.bincount(group, weights=even)
    n_odd = np.bincount(group, weights=~even)
    majority = np.sign(n_even - n_odd)  # +1 even, -1 odd, 0: they cancel out
    candidate = np.flatnonzero(np.where(even, 1, -1) == majority[group])
    _, first = np.unique(group[candidate], return_index=True)
    keep = np.sort(candidate[first])
    return faces[keep], int(len(faces) - len(keep))


def decimate(mesh: trimesh.Trimesh, target_faces: int) -> tuple[trimesh.Trimesh, int]:
    """Quadric edge-collapse (fast_simplification) down to about ``target_faces`` faces; returns the
    mesh and the number of duplicate faces it left that were removed (see remove_duplicate_faces)."""
    if target_faces >= len(mesh.faces):
        return mesh, 0
    pts, tris = fast_simplification.simplify(
        mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32), target_count=int(target_faces)
    )
    tris, removed = remove_duplicate_faces(np.asarray(tris, np.int64))
    return _mesh(pts, tris), removed


def split_pinched_edges(mesh: trimesh.Trimesh, limit: int = 1000) -> tuple[trimesh.Trimesh, int]:
    """Part the sheets that meet on one edge (an edge of more than two faces, where a decimation's collapse pinched two
    sheets together): at the end of a chain of such edges, the faces round the vertex are grouped by the ordinary edges
    they share, and every group but the first gets its own copy of the vertex; then the edges are counted again (a
    split frees the next vertex of the chain), at most ``limit`` vertices. The sheets then touch at a point and each
    edge has two faces. Returns the mesh and how many vertex copies were made (each moved a hundredth of the way to its
    faces' middle, so that a program that merges coincident vertices does not pinch them again)."""
    def pinched_edges(tris: np.ndarray) -> np.ndarray:
        edges = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        unique, counts = np.unique(edges, axis=0, return_counts=True)
        return unique[counts > 2]

    pinched = pinched_edges(mesh.faces)
    if not len(pinched):
        return mesh, 0
    # every face on an edge of a pinched edge's vertex is a face round that vertex: work on those alone
    rows = np.flatnonzero(np.isin(mesh.faces, np.unique(pinched)).any(axis=1))
    faces, vertices, made = mesh.faces[rows].copy(), mesh.vertices.copy(), 0
    for _ in range(limit):
        pinched = pinched_edges(faces) if made else pinched
        if not len(pinched):
            break
        bad = {tuple(e) for e in pinched.tolist()}
        ends, times = np.unique(pinched, return_counts=True)
        v = int(ends[np.argmin(times)])  # the end of a chain of pinched edges: round it one cut leaves a sheet whole
        fan = np.flatnonzero((faces == v).any(axis=1))
        sides: dict[int, list[int]] = {}
        for i, f in enumerate(faces[fan]):
            for w in f[f != v]:
                sides.setdefault(int(w), []).append(i)
        links = [around for w, around in sides.items() if len(around) == 2 and (min(v, w), max(v, w)) not in bad]
        labels = graph.connected_component_labels(np.asarray(links, np.int64).reshape(-1, 2), node_count=len(fan))
        groups: dict[int, list[int]] = {}
        for i, label in enumerate(labels):
            groups.setdefault(int(label), []).append(i)
        if len(groups) < 2:
            break  # a pinch this cannot part: the caller sees the mesh is still not watertight
        for members in list(groups.values())[1:]:
            group = fan[members]
            toward = vertices[faces[group]].reshape(-1, 3).mean(axis=0)  # a hair into its own sheet: a tool that
            vertices = np.vstack([vertices, vertices[v] + 0.01 * (toward - vertices[v])])  # merges copies keeps it
            faces[group] = np.where(faces[group] == v, len(vertices) - 1, faces[group])
            made += 1
    out = mesh.faces.copy()
    out[rows] = faces
    return trimesh.Trimesh(vertices, out, process=False), made


CLOSED_DECIMATION_TARGETS = (1.0, 0.97, 1.03)
"""`decimate_closed` tries these multiples of the face target in turn (another target collapses other edges)."""


def decimate_closed(mesh: trimesh.Trimesh, target_faces: int) -> tuple[trimesh.Trimesh, int, int]:
    """`decimate` for a watertight mesh that must stay so: an edge collapse can pinch two sheets onto one edge (four
    faces on it), which `split_pinched_edges` parts again; should the mesh still not be watertight, the next target of
    CLOSED_DECIMATION_TARGETS is tried, and when none works the mesh is kept as it is. Returns the mesh, the duplicate
    faces removed and the tries made (0: kept undecimated)."""
    for i, factor in enumerate(CLOSED_DECIMATION_TARGETS, start=1):
        out, folded = decimate(mesh, max(4, int(target_faces * factor)))
        if not out.is_watertight:
            out, _ = split_pinched_edges(out)
        if out.is_watertight:
            return out, folded, i
    return mesh, 0, 0


def _bbox(mesh: trimesh.Trimesh) -> list[list[float]]:
    if len(mesh.vertices) == 0:
        return []
    return [mesh.vertices.min(axis=0).tolist(), mesh.vertices.max(axis=0).tolist()]


def clean_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    aabb: np.ndarray,
    min_component_fraction: float = 0.05,
    smooth_iters: int = 0,
    target_faces: int | None = None,
    seen_fn: SeenFn | None = None,
    ground: np.ndarray | None = None,
    ground_margin: float = 0.0,
    keep_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    closed: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Crop to the scene box, remove floaters and (with ``seen_fn``) hidden faces, optionally
    Taubin-smooth and decimate. ``closed``: a watertight mesh stays watertight (`decimate_closed`).

    vertices: (V, 3) scene units; faces: (F, 3) vertex indices; aabb: (2, 3) scene box.
    Floater rule: a face-connected component is kept when its area is at least
    ``min_component_fraction`` × the largest component's area (0 keeps everything).
    Taubin smoothing (λ = 0.5, ν = 0.53, ``smooth_iters`` iterations) removes marching-cubes
    staircase without shrinking the object the way plain Laplacian smoothing does.

    Returns ``(vertices (V', 3) float32, faces (F', 3) int64, report)``; the report holds counts
    before/after every step, the component rule and how many were removed, watertightness,
    surface area and bounding box. ``ground`` (nx, ny, nz, d): faces within ``ground_margin`` of that plane or
    below it are cut (`cut_below_plane`) before floaters are counted; ``keep_fn`` (e.g. the photos' masks) drops
    the faces of vertices it rejects, also before.
    """
    if target_faces is not None and target_faces < 4:
        raise ValueError(f"target_faces must be >= 4 (a tetrahedron), got {target_faces}")
    mesh = _mesh(vertices, faces)
    report: dict = {"input": {"vertices": int(len(vertices)), "faces": int(len(faces))}, "merged": _counts(mesh)}
    mesh = crop_to_aabb(mesh, aabb)
    report["cropped"] = _counts(mesh)
    if ground is not None:
        mesh, cut = cut_below_plane(mesh, ground, ground_margin)
        report["ground_cut"] = {**_counts(mesh), "faces_removed": cut, "margin": float(ground_margin)}
    if keep_fn is not None and len(mesh.faces):
        mesh, cut = keep_vertices(mesh, keep_fn)
        report["masked"] = {**_counts(mesh), "faces_removed": cut}
    mesh, report["components"] = remove_small_components(mesh, min_component_fraction)
    report["floaters_removed"] = _counts(mesh)
    if seen_fn is not None and len(mesh.faces):
        mesh, report["hidden"] = remove_hidden_faces(mesh, seen_fn)
        report["hidden_removed"] = _counts(mesh)
    if smooth_iters > 0 and len(mesh.faces):
        smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smooth_iters)
        report["smoothed"] = {"iterations": int(smooth_iters)}
    if target_faces is not None and len(mesh.faces):
        if closed and mesh.is_watertight:
            mesh, folded, tries = decimate_closed(mesh, target_faces)
        else:
            (mesh, folded), tries = decimate(mesh, target_faces), None
        report["decimated"] = {**_counts(mesh), "target_faces": int(target_faces), "duplicate_faces_removed": folded}
        if tries is not None:
            report["decimated"]["closed_tries"] = tries
    if (seen_fn is not None or target_faces is not None) and len(mesh.faces):
        # what the photos saw of the walls inside the shell, and slivers decimation cut off, are left as crumbs
        mesh, report["crumbs"] = remove_small_components(mesh, min_component_fraction)
    report["output"] = {
        **_counts(mesh),
        "watertight": bool(mesh.is_watertight) if len(mesh.faces) else False,
        "area": float(mesh.area),
        "bbox": _bbox(mesh),
    }
    return mesh.vertices.astype(np.float32), mesh.faces.astype(np.int64), report
