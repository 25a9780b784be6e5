"""Per-vertex colors for the extracted mesh: from the radiance field, or baked from the input photos.

Frames: vertices, normals and camera poses are in the normalized scene frame; ``c2ws`` are 4×4
camera-to-world matrices in the OpenGL convention (camera looks down -Z, +Y up, +X right); pixel
(i, j) covers [i, i+1) × [j, j+1) with its centre at (i + 0.5, j + 0.5); colors are floats in [0, 1]
in the images' own encoding (sRGB for photos).
"""
from __future__ import annotations

from typing import Callable, Literal, Sequence

import numpy as np
import torch
from scipy.ndimage import maximum_filter, minimum_filter
from scipy.spatial import cKDTree

from recon.camera import MIN_DEPTH, project

RadianceFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``radiance_fn(x: (M, 3), d: (M, 3) unit view directions) -> (M, 3)`` RGB in [0, 1]."""


def colors_from_field(
    radiance_fn: RadianceFn,
    vertices: np.ndarray,
    normals: np.ndarray,
    chunk: int = 2**16,
    device: torch.device | str = "cpu",
) -> np.ndarray:
    """Ask the field for each vertex's color as seen head-on from outside.

    The view direction is the inward normal ``d = -n`` (a camera in front of the surface looking at
    it), so view-dependent fields return their frontal, mostly diffuse color.
    vertices, normals: (V, 3) scene frame, normals outward; returns (V, 3) float32 in [0, 1].
    """
    verts = np.asarray(vertices, np.float32)
    dirs = -np.asarray(normals, np.float32)
    dirs = dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    out = np.empty((len(verts), 3), np.float32)
    with torch.no_grad():
        for s in range(0, len(verts), chunk):
            x = torch.from_numpy(verts[s : s + chunk]).to(device)
            d = torch.from_numpy(dirs[s : s + chunk]).to(device)
            out[s : s + chunk] = radiance_fn(x, d).reshape(-1, 3).float().cpu().numpy()
    return np.clip(out, 0.0, 1.0)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of image (H, W, C) at continuous pixel coords uv (N, 2) → (N, C), edge-clamped."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-column weighted median: values (K, N, C), weights (K, N) ≥ 0 with a positive column sum. Sorted along
    the last axis of a (N, C, K) copy: a point's K samples side by side sort 2–3× faster than strided ones."""
    v = np.ascontiguousarray(values.transpose(1, 2, 0))  # (N, C, K)
    order = np.argsort(v, axis=-1)
    v = np.take_along_axis(v, order, axis=-1)
    w = np.take_along_axis(np.broadcast_to(weights.T[:, None, :], v.shape), order, axis=-1)
    cum = np.cumsum(w, axis=-1)
    first = np.argmax(cum >= 0.5 * cum[..., -1:], axis=-1)  # (N, C)
    return np.take_along_axis(v, first[..., None], axis=-1)[..., 0]


def _photo_samples_numpy(
    verts: np.ndarray, nrm: np.ndarray, imgs: Sequence[np.ndarray], scales: Sequence[float], c2ws: np.ndarray,
    intr: np.ndarray, depths: Sequence[np.ndarray | None] | None, depth_tol: float, depth_kind: Literal["ray", "z"],
    min_cos: float, reduce: Literal["median", "mean"], chunk: int,
) -> tuple[np.ndarray, np.ndarray]:
    """`colors_from_photos`' colours and seen flags (before the unseen points' fallback), a view at a time in numpy:
    the reference `photo_samples_torch` is held to."""
    k = len(imgs)
    colors = np.zeros((len(verts), 3), np.float32)
    seen = np.zeros(len(verts), bool)
    for s in range(0, len(verts), chunk):
        x, n = verts[s : s + chunk], nrm[s : s + chunk]
        samples = np.zeros((k, len(x), 3), np.float32)
        weights = np.zeros((k, len(x)), np.float32)
        for view in range(k):
            d = depths[view] if depths is not None else None
            bounds = (d, d) if d is not None else None
            ok, uv, cos = _visible_in_view(x, n, imgs[view].shape[:2], c2ws[view], intr[view], bounds, depth_tol, depth_kind, min_cos)
            if ok.any():
                samples[view, ok] = sample_bilinear(imgs[view], uv[ok])[:, :3] * scales[view]
                weights[view, ok] = cos[ok]
        total = weights.sum(axis=0)
        hit = total > 0
        seen[s : s + chunk] = hit
        if not hit.any():
            continue
        if reduce == "median":
            colors[s : s + chunk][hit] = _weighted_median(samples[:, hit], weights[:, hit])
        else:
            colors[s : s + chunk][hit] = np.einsum("kn,knc->nc", weights[:, hit], samples[:, hit]) / total[hit, None]
    return colors, seen


class _TorchCameras:
    """K cameras of one image size on a device, for testing points against every view at once (`visible`): the
    torch twin of `_visible_in_view`, shared by the bake and the view count. ``lows``/``highs``: the K depth maps'
    lowest and highest depth a point may match (one map for both in the bake), or None."""

    def __init__(self, c2ws: np.ndarray, intrinsics: np.ndarray, hw: tuple[int, int], device: torch.device,
                 lows: torch.Tensor | None = None, highs: torch.Tensor | None = None) -> None:
        f64 = {"dtype": torch.float64, "device": device}
        self.k, (self.h, self.w) = len(c2ws), hw
        self.rot = torch.as_tensor(c2ws[:, :3, :3], **f64)  # (K, 3, 3)
        self.centre = torch.as_tensor(c2ws[:, :3, 3], **f64)[:, None, :]  # (K, 1, 3)
        self.fx, self.fy, self.cx, self.cy = (torch.as_tensor(intrinsics[:, i], **f64)[:, None] for i in range(4))
        self.base = (torch.arange(self.k, device=device) * (self.h * self.w))[:, None]  # each view's first pixel
        self.lows = None if lows is None else lows.reshape(-1)
        self.highs = None if highs is None else highs.reshape(-1)

    def visible(self, x: torch.Tensor, n: torch.Tensor, depth_tol: float, depth_kind: Literal["ray", "z"],
                min_cos: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points x, n (N, 3) float64 in every view: ok (K, N) (in front, facing the camera, inside the image, the
        depth maps' pixel within ``depth_tol``), u, v (K, N) pixel coordinates and cos θ (K, N)."""
        h, w = self.h, self.w
        cam = torch.matmul(x[None] - self.centre, self.rot)  # world_to_camera in every view: (K, N, 3)
        z = -cam[..., 2]
        safe = torch.where(z.abs() > MIN_DEPTH, z, torch.full_like(z, MIN_DEPTH))
        u, v = self.cx + self.fx * cam[..., 0] / safe, self.cy - self.fy * cam[..., 1] / safe
        to_cam = self.centre - x[None]
        dist = torch.linalg.vector_norm(to_cam, dim=-1)
        cos = (n[None] * to_cam).sum(-1) / dist.clamp_min(1e-12)
        ok = (z > 0) & (cos > min_cos) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        if self.lows is not None and self.highs is not None:
            col = torch.where(ok, u, 0.0).long().clamp(0, w - 1)
            row = torch.where(ok, v, 0.0).long().clamp(0, h - 1)
            pixel = self.base + row * w + col
            mine = dist if depth_kind == "ray" else z
            # in the maps' own dtype, as the reference subtracts the tolerance
            ok &= (mine > (self.lows[pixel] - depth_tol).to(mine.dtype)) & (mine < (self.highs[pixel] + depth_tol).to(mine.dtype))
        return ok, u, v, cos


def photo_samples_torch(
    verts: np.ndarray, nrm: np.ndarray, images: Sequence[np.ndarray], scales: Sequence[float], c2ws: np.ndarray,
    intrinsics: np.ndarray, depths: Sequence[np.ndarray] | None, depth_tol: float, depth_kind: Literal["ray", "z"],
    min_cos: float, reduce: Literal["median", "mean"], device: torch.device, chunk: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`colors_from_photos`' colours and seen flags (before the unseen points' fallback) in torch on ``device``, every
    view of a chunk of points at once: the same visibility test (`_TorchCameras.visible`), bilinear samples and
    cos-weighted median or mean, in float64 where the numpy reference computes in float64. Images: K arrays of one
    size (H, W, ≥3)."""
    f64 = {"dtype": torch.float64, "device": device}
    k = len(images)
    chunk = chunk or max(1024, 2**23 // k)  # points a pass: its (K, N, 3) float64 tensors stay ~200 MB each
    h, w = images[0].shape[:2]
    pixels = torch.stack([torch.as_tensor(np.ascontiguousarray(im[..., :3])) for im in images]).to(device)
    pixels = pixels.reshape(k * h * w, 3)
    scale = torch.as_tensor(np.asarray(scales, np.float64), **f64)[:, None, None]
    maps = None if depths is None else torch.stack([torch.as_tensor(np.asarray(d)) for d in depths]).to(device)
    cameras = _TorchCameras(c2ws, intrinsics, (h, w), device, maps, maps)
    base = cameras.base
    colors = np.zeros((len(verts), 3), np.float32)
    seen = np.zeros(len(verts), bool)
    for s in range(0, len(verts), chunk):
        x = torch.as_tensor(verts[s : s + chunk], **f64)
        n = torch.as_tensor(nrm[s : s + chunk], **f64)
        ok, u, v, cos = cameras.visible(x, n, depth_tol, depth_kind, min_cos)
        # bilinear, edge-clamped (sample_bilinear)
        bx = (u - 0.5).clamp(0, w - 1)
        by = (v - 0.5).clamp(0, h - 1)
        x0 = bx.floor().long().clamp(max=w - 2 if w > 1 else 0)
        y0 = by.floor().long().clamp(max=h - 2 if h > 1 else 0)
        x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
        tx, ty = (bx - x0)[..., None], (by - y0)[..., None]

        def at(rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
            return pixels[base + rows * w + cols].to(torch.float64)

        top = at(y0, x0) * (1 - tx) + at(y0, x1) * tx
        bottom = at(y1, x0) * (1 - tx) + at(y1, x1) * tx
        samples = torch.where(ok[..., None], (top * (1 - ty) + bottom * ty) * scale, 0.0).to(torch.float32)
        weights = torch.where(ok, cos, 0.0).to(torch.float32)  # (K, N)
        total = weights.sum(0)
        hit = total > 0
        if reduce == "median":
            vals, order = torch.sort(samples.permute(1, 2, 0), dim=-1)  # (N, 3, K)
            wts = torch.gather(weights.T[:, None, :].expand_as(vals), -1, order)
            cum = torch.cumsum(wts, -1)
            first = (cum >= 0.5 * cum[..., -1:]).int().argmax(-1, keepdim=True)
            out = torch.gather(vals, -1, first)[..., 0]
        else:
            out = torch.einsum("kn,knc->nc", weights, samples) / total.clamp_min(1e-30)[:, None]
        hit_np = hit.cpu().numpy()
        colors[s : s + chunk][hit_np] = out[hit].cpu().numpy()
        seen[s : s + chunk] = hit_np
    return colors, seen


def _visible_in_view(
    x: np.ndarray, n: np.ndarray, hw: tuple[int, int], c2w: np.ndarray, intrinsics: np.ndarray,
    depth: tuple[np.ndarray, np.ndarray] | None, depth_tol: float, depth_kind: Literal["ray", "z"], min_cos: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which points x (N, 3) one camera sees: in the image, in front, facing it (n · to-camera > min_cos)
    and, with ``depth`` = (lowest, highest) maps (H, W), at a distance in [lowest - tol, highest + tol] read at
    their pixel (nearest, so silhouettes do not blend depths). Returns ok (N,) bool, uv (N, 2) and cos θ (N,)."""
    h, w = hw
    uv, z = project(x, c2w, intrinsics)
    to_cam = c2w[:3, 3] - x
    dist = np.linalg.norm(to_cam, axis=1)
    cos = np.einsum("ij,ij->i", n, to_cam) / np.maximum(dist, 1e-12)
    ok = (z > 0) & (cos > min_cos) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if depth is not None and ok.any():
        lo, hi = np.asarray(depth[0]), np.asarray(depth[1])
        px = np.clip(uv[ok].astype(np.int64), 0, [w - 1, h - 1])
        mine = dist[ok] if depth_kind == "ray" else z[ok]
        ok[np.flatnonzero(ok)] = (mine > lo[px[:, 1], px[:, 0]] - depth_tol) & (mine < hi[px[:, 1], px[:, 0]] + depth_tol)
    return ok, uv, cos


def seen_by_views(
    vertices: np.ndarray,
    normals: np.ndarray,
    depths: Sequence[np.ndarray],
    c2ws: np.ndarray,
    intrinsics: np.ndarray,
    depth_tol: float,
    depth_kind: Literal["ray", "z"] = "ray",
    min_cos: float = 0.0,
    chunk: int = 2**16,
    device: torch.device | str | None = None,
) -> np.ndarray:
    """How many views see each vertex (V,) int: it projects into the view, faces the camera
    (cos θ > min_cos, normals outward) and its distance matches the view's depth map (H, W) within
    depth_tol (scene units) of the depths in the 3×3 pixels around it (so grazing faces and silhouettes,
    where depth jumps between neighbouring pixels, still match). The inner walls of a hollow or soft
    field fail both tests: they lie behind the surface the photos show and face away from the cameras.
    ``device``: count in torch there, every view of a chunk at once (maps of one size; the numpy loop,
    ``device=None``, is its reference): the mesh stage passes its CUDA device."""
    verts, nrm = np.asarray(vertices, np.float64), np.asarray(normals, np.float64)
    c2ws, intr = np.asarray(c2ws, np.float64), np.asarray(intrinsics, np.float64)
    if device is not None and len(depths) and len({np.shape(d) for d in depths}) == 1 and len(verts):
        return _seen_by_views_torch(verts, nrm, depths, c2ws, intr, depth_tol, depth_kind, min_cos, torch.device(device))
    ranges = [(minimum_filter(np.asarray(d), size=3, mode="nearest"), maximum_filter(np.asarray(d), size=3, mode="nearest"))
              for d in depths]
    counts = np.zeros(len(verts), np.int32)
    for s in range(0, len(verts), chunk):
        x, n = verts[s : s + chunk], nrm[s : s + chunk]
        for rng, c2w, k in zip(ranges, c2ws, intr):
            ok, _, _ = _visible_in_view(x, n, rng[0].shape[:2], c2w, k, rng, depth_tol, depth_kind, min_cos)
            counts[s : s + chunk] += ok
    return counts


def _seen_by_views_torch(
    verts: np.ndarray, nrm: np.ndarray, depths: Sequence[np.ndarray], c2ws: np.ndarray, intrinsics: np.ndarray,
    depth_tol: float, depth_kind: Literal["ray", "z"], min_cos: float, device: torch.device,
) -> np.ndarray:
    """`seen_by_views` in torch on ``device``: the 3×3 lowest and highest depths by pooling (a window's padding
    never wins, so the image's edge acts as scipy's "nearest" mode), then `_TorchCameras.visible`."""
    maps = torch.stack([torch.as_tensor(np.asarray(d)) for d in depths]).to(device)[:, None]  # (K, 1, H, W)
    highs = torch.nn.functional.max_pool2d(maps, 3, stride=1, padding=1)[:, 0]
    lows = -torch.nn.functional.max_pool2d(-maps, 3, stride=1, padding=1)[:, 0]
    cameras = _TorchCameras(c2ws, intrinsics, tuple(maps.shape[-2:]), device, lows, highs)
    chunk = max(1024, 2**23 // cameras.k)  # points a pass, as the bake's: its (K, N, 3) float64 tensors stay ~200 MB
    counts = np.zeros(len(verts), np.int32)
    f64 = {"dtype": torch.float64, "device": device}
    for s in range(0, len(verts), chunk):
        x = torch.as_tensor(verts[s : s + chunk], **f64)
        n = torch.as_tensor(nrm[s : s + chunk], **f64)
        ok = cameras.visible(x, n, depth_tol, depth_kind, min_cos)[0]
        counts[s : s + chunk] = ok.sum(0, dtype=torch.int32).cpu().numpy()
    return counts


def colors_from_photos(
    points: np.ndarray,
    normals: np.ndarray,
    images: Sequence[np.ndarray],
    c2ws: np.ndarray,
    intrinsics: np.ndarray,
    depths: Sequence[np.ndarray | None] | None = None,
    fallback: np.ndarray | None = None,
    depth_tol: float | None = None,
    depth_kind: Literal["ray", "z"] = "ray",
    min_cos: float = 0.05,
    reduce: Literal["median", "mean"] = "median",
    chunk: int = 2**15,
    device: torch.device | str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Colors of surface points from the photos that see each point; robust to occluders and highlights.

    One function for every kind of surface sample: mesh vertices (vertex colors) and the surface points
    under texel centres (`texture.bake_texture`), so both get the same visibility test and average.

    A view contributes to a point when the point projects inside the image, lies in front of the
    camera, faces it (cos θ = n · (cam − x)/|cam − x| > ``min_cos``), and — when a depth map is given
    for that view — is not occluded: ``|depth(point) − depth_map(pixel)| < depth_tol``. The depth map
    is read at the pixel that contains the projection (nearest, so silhouettes do not blend depths).
    ``depth_kind`` says what the maps hold: "ray" = distance from the camera centre along the pixel's
    ray (what NeRF renderers output as expected t with unit directions), "z" = depth along the optical
    axis. ``depth_tol`` is in scene units; by default 1 % of the points' bounding-box diagonal
    (≈ 0.03 for an object filling the normalized [-1, 1]³ box, ~8 cells of a 512³ grid), loose enough
    for the blur of rendered depth, tight enough to reject a surface behind another. Without depth
    maps only back-facing is culled, so concave objects can pick up occluders' colors. Pass ``depth_tol``
    explicitly when baking a surface in several calls (chunks, or vertices and texels alike) so every call
    uses the same one.

    The contributing samples are combined per channel with a weighted median (``reduce="median"``,
    weights cos θ: robust to a minority of wrong samples such as highlights and missed occlusions) or
    a weighted mean. Points that no view sees take ``fallback`` (e.g. field colors, (V, 3)) when
    given, otherwise the color of the nearest seen point.

    points, normals: (V, 3) scene frame, normals outward unit; images: K arrays (H, W, 3) float in
    [0, 1] (uint8 is rescaled); c2ws: (K, 4, 4) OpenGL; intrinsics: (K, 4) fx, fy, cx, cy; depths: K
    maps (H, W) or None entries; extra image channels (alpha) are ignored. ``device``: compute the same in torch
    there, all views at once (`photo_samples_torch`; the numpy loop, ``device=None``, is its reference): the mesh
    stage passes its CUDA device, where baking a texture in numpy would be most of the stage's time.
    Returns ``colors (V, 3) float32`` and ``seen (V,) bool``.
    """
    verts = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    c2ws, intr = np.asarray(c2ws, np.float64), np.asarray(intrinsics, np.float64)
    k = len(images)
    if c2ws.shape != (k, 4, 4) or intr.shape != (k, 4):
        raise ValueError(f"{k} images need c2ws (K, 4, 4) and intrinsics (K, 4); got {c2ws.shape}, {intr.shape}")
    if depths is not None and len(depths) != k:
        raise ValueError(f"depths must have one entry (map or None) per image: {len(depths)} != {k}")
    if depth_tol is None:
        depth_tol = 0.01 * float(np.linalg.norm(np.ptp(verts, axis=0))) if len(verts) else 0.0
    imgs = [np.asarray(im) for im in images]  # no float copies of all photos: scaled when sampled
    scales = [1 / 255 if im.dtype == np.uint8 else 1.0 for im in imgs]

    same_size = len({im.shape[:2] for im in imgs}) == 1 and (depths is None or all(d is not None for d in depths))
    if device is not None and k and same_size and len(verts):
        colors, seen = photo_samples_torch(verts, nrm, imgs, scales, c2ws, intr, depths, depth_tol, depth_kind,
                                           min_cos, reduce, torch.device(device))
    else:
        colors, seen = _photo_samples_numpy(verts, nrm, imgs, scales, c2ws, intr, depths, depth_tol, depth_kind,
                                            min_cos, reduce, chunk)

    if not seen.all():
        if fallback is not None:
            colors[~seen] = np.asarray(fallback, np.float32)[~seen]
        elif seen.any():
            _, nearest = cKDTree(verts[seen]).query(verts[~seen])
            colors[~seen] = colors[seen][nearest]
        else:
            colors[:] = 0.5
    return np.clip(colors, 0.0, 1.0), seen
