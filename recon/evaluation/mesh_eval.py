"""Geometry accuracy of a scene's mesh against a ground-truth mesh: `recon eval SCENE --gt-mesh GT.ply`.

Our mesh lives in the frame it was exported in (mesh_report.json says which). It is mapped back to
the normalized scene frame, then to the source frame with the stored normalization similarity
(`scene.source_from_world`). With known poses (transforms.json, NeRF-synthetic, .npz) the source
frame IS the ground truth's frame, so this is exact. With SfM poses the source frame is COLMAP's
arbitrary one: when the capture folder (or the GT mesh's folder) holds a transforms.json with the
true poses (the fixture generator writes one), a Sim(3) is fitted from our camera centres (source
frame) to the true ones, frames matched by file name, leaving out the few SfM misplaced, and its residual reported.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import trimesh

from recon.atomic import read_json
from recon.capture.normalization import transform_c2w
from recon.capture.scene import UNSURE_MASK_FOLDER, Frame, Scene, load_scene, parse_frames, pinhole_mask
from recon.errors import ReconError
from recon.geometry.compare import Camera, chamfer_fscore, fit_sim3_robust, icp_sim3, sample_surface

SCENE_FOLDER = "02_scene"
MESH_FOLDER = "04_mesh"
KNOWN_POSES = ("transforms", "nerf_synthetic", "npz")
"""source_kind values whose source frame is the true world frame (no SfM gauge freedom)."""


def _load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise ReconError(f"Cannot read the mesh {path}: {exc}. Check the file (PLY/OBJ/GLB/STL).") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ReconError(f"{path} holds no triangles; give a surface mesh.")
    return mesh


def our_mesh_in_scene_frame(scene_dir: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The scene's mesh.ply mapped back to the normalized scene frame: vertices (V, 3), faces (F, 3), report.

    mesh.ply is written in the export frame with +Z up (no axis change); the report's
    ``export.transform`` (4×4, scene → export frame) is inverted.
    """
    folder = scene_dir / MESH_FOLDER
    try:
        report = read_json(folder / "mesh_report.json")
    except (OSError, ValueError) as exc:
        raise ReconError(f"No readable mesh report in {folder} ({exc}). Run the mesh stage first: recon mesh {scene_dir}.") from None
    mesh = _load_mesh(folder / report.get("export", {}).get("files", {}).get("ply", "mesh.ply"))
    transform = np.asarray(report["export"]["transform"], np.float64)
    inv = np.linalg.inv(transform)
    vertices = np.asarray(mesh.vertices, np.float64) @ inv[:3, :3].T + inv[:3, 3]
    faces = np.asarray(mesh.faces, np.int64)
    if np.linalg.det(inv[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return vertices, faces, report


def _true_poses(candidates: Sequence[Path]) -> tuple[Path, dict[str, np.ndarray], list[Frame]] | None:
    """The first transforms.json among candidate folders: path, true camera centres by file name, and its frames."""
    for folder in candidates:
        path = folder / "transforms.json" if folder.is_dir() else folder
        if path.name == "transforms.json" and path.is_file():
            try:
                doc = read_json(path)
                frames = parse_frames(doc, base=path.parent, source=path, check_files=False)
            except (ValueError, ReconError) as exc:
                raise ReconError(f"The true poses {path} are unreadable ({exc}).") from None
            return path, {f.name: f.c2w[:3, 3] for f in frames}, frames
    return None


def _cameras(frames: Sequence[Frame], to_truth: np.ndarray | None = None) -> list[Camera]:
    """The frames' cameras (`recon.geometry.compare.Camera`), moved into the truth's frame by the similarity
    to_truth (4, 4) when given (its scale leaves the rotation: c2w stays rigid)."""
    return [(np.asarray(f.c2w, np.float64) if to_truth is None else transform_c2w(to_truth, f.c2w),
             (f.fl_x, f.fl_y, f.cx, f.cy), (f.h, f.w)) for f in frames]


def align_sfm_to_truth(scene: Scene, truth: dict[str, np.ndarray]) -> tuple[np.ndarray, dict]:
    """4×4 similarity source (SfM) frame → true frame fitted on camera centres matched by file name
    (then by stem), leaving out the cameras SfM misplaced (`fit_sim3_robust`), and its residuals over the cameras
    it was fitted on: rms and max in true units and relative to the camera-rig radius (rms distance of the true
    centres from their mean); the cameras left out are listed with theirs."""
    by_stem = {Path(n).stem: c for n, c in truth.items()}
    src, dst, names = [], [], []
    for f in scene.frames:
        c = truth.get(f.name, by_stem.get(f.stem))
        if c is not None:
            src.append(scene.source_from_world[:3, :3] @ f.c2w[:3, 3] + scene.source_from_world[:3, 3])
            dst.append(c)
            names.append(f.name)
    if len(src) < 3:
        raise ReconError(
            f"Only {len(src)} of our {len(scene.frames)} cameras match the true poses by file name; need 3 or more "
            f"to align the SfM frame to the ground truth. Check that the photos keep their original names."
        )
    src_a, dst_a = np.asarray(src), np.asarray(dst)
    s, rot, t, used = fit_sim3_robust(src_a, dst_a)
    res = np.linalg.norm(s * src_a @ rot.T + t - dst_a, axis=1)
    radius = float(np.sqrt(((dst_a - dst_a.mean(axis=0)) ** 2).sum(axis=1).mean()))
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = s * rot, t
    fitted = res[used]
    info = {
        "cameras_matched": len(src),
        "cameras_fitted": int(used.sum()),
        "scale": s,
        "residual_rms": float(np.sqrt((fitted**2).mean())),
        "residual_max": float(fitted.max()),
        "residual_rms_rel": float(np.sqrt((fitted**2).mean()) / radius) if radius > 0 else float("nan"),
        "worst_camera": names[int(np.flatnonzero(used)[fitted.argmax()])],
        "cameras_left_out": {names[i]: float(res[i]) for i in np.flatnonzero(~used)},
    }
    return sim, info


def in_truth_frame(scene_dir: Path, gt_mesh: Path) -> tuple[trimesh.Trimesh, trimesh.Trimesh, dict[str, Any],
                                                             list[Camera], dict]:
    """(our mesh, the true mesh, the alignment used and its residual, the training photos' cameras, our mesh report),
    both meshes in the truth's frame: exact for known poses, else a Sim(3) fit of our camera centres to the true
    poses in a transforms.json beside the capture or the true mesh."""
    scene_dir, gt_mesh = Path(scene_dir), Path(gt_mesh)
    vertices, faces, report = our_mesh_in_scene_frame(scene_dir)
    scene = load_scene(scene_dir / SCENE_FOLDER)
    to_source = scene.source_from_world
    v_src = vertices @ to_source[:3, :3].T + to_source[:3, 3]
    if np.linalg.det(to_source[:3, :3]) < 0:
        faces = faces[:, ::-1]
    alignment: dict[str, Any]
    if scene.source_kind in KNOWN_POSES:
        v_gt = v_src
        alignment = {"method": f"exact: known poses ({scene.source_kind}), inverse normalization similarity",
                     "exact": True}
        cameras = _cameras(scene.frames, to_source)
    else:
        candidates = [gt_mesh.parent]
        try:
            source = read_json(scene_dir / "manifest.json").get("source")
        except (OSError, ValueError, AttributeError):
            source = None
        source = source if isinstance(source, str) else None
        if source:
            candidates = [Path(source), Path(source).parent, gt_mesh.parent]
        found = _true_poses(candidates)
        if found is None:
            raise ReconError(
                f"The poses of {scene_dir} come from SfM ({scene.source_kind}), whose frame is arbitrary, and no "
                f"transforms.json with the true poses was found in {', '.join(str(c) for c in candidates)} to align it "
                f"to {gt_mesh}. Put the true poses next to the GT mesh as transforms.json."
            )
        path, truth, true_frames = found
        cameras = _cameras(true_frames)
        sim, fit = align_sfm_to_truth(scene, truth)
        v_gt = v_src @ sim[:3, :3].T + sim[:3, 3]
        alignment = {"method": f"Sim(3) fit of our cameras to the true ones in {path}", "exact": False, **fit}
    return trimesh.Trimesh(v_gt, faces, process=False), _load_mesh(gt_mesh), alignment, cameras, report


def compare_to_gt(
    scene_dir: Path, gt_mesh: Path, thresholds: Sequence[float] = (0.01, 0.005), n_samples: int = 200_000
) -> dict[str, Any]:
    """Chamfer-L1 and precision/recall/F-score of the scene's mesh against gt_mesh, in the GT's frame.

    thresholds: fractions of the GT bounding-box diagonal (1 % and 0.5 % by default). Returns a flat,
    JSON-ready dict (see `format_comparison`): the alignment used and its residual, ``chamfer_l1``
    (GT units), ``chamfer_l1_rel`` (÷ GT diagonal), ``precision@τ``, ``recall@τ``, ``fscore@τ``, and when both
    meshes are watertight ``volume_ratio`` (ours ÷ the truth's).
    """
    scene_dir, gt_mesh = Path(scene_dir), Path(gt_mesh)
    aligned, gt, alignment, cameras, report = in_truth_frame(scene_dir, gt_mesh)
    v_gt, faces = np.asarray(aligned.vertices), np.asarray(aligned.faces)
    metrics = chamfer_fscore((v_gt, faces), gt, thresholds=thresholds, n_samples=n_samples, cameras=cameras)
    out = {
        "mesh": str(scene_dir / MESH_FOLDER / report.get("export", {}).get("files", {}).get("ply", "mesh.ply")),
        "gt_mesh": str(gt_mesh),
        "alignment": alignment,
        "thresholds": list(thresholds),
        **metrics,
    }
    ours = trimesh.Trimesh(v_gt, faces)  # vertices merged: a solid's seams do not open it
    if ours.is_watertight and gt.is_watertight and abs(gt.volume) > 0:  # two solids: how much of the true one
        out["volume_ratio"] = float(ours.volume / gt.volume)
    if not alignment["exact"]:  # SfM: also the shape's accuracy free of SfM's scale error
        out["icp_refined"] = icp_refined(v_gt, faces, gt, thresholds, n_samples)
    return out


def icp_refined(
    vertices: np.ndarray, faces: np.ndarray, gt: trimesh.Trimesh, thresholds: Sequence[float], n_samples: int
) -> dict[str, Any]:
    """The comparison after an ICP refinement of the camera alignment (`icp_sim3`, Tanks and Temples'
    protocol): the correction it applied (scale, rotation in degrees, translation ÷ GT diagonal) and the metrics."""
    s, rot, t = icp_sim3(sample_surface((vertices, faces), 50_000, seed=2), sample_surface(gt, 50_000, seed=3))
    metrics = chamfer_fscore((s * vertices @ rot.T + t, faces), gt, thresholds=thresholds, n_samples=n_samples)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    return {"scale": float(s), "rotation_deg": angle, "translation_rel": float(np.linalg.norm(t) / metrics["gt_diagonal"]),
            **metrics}


def format_comparison(result: dict[str, Any]) -> str:
    """Human-readable lines for a `compare_to_gt` result (what `recon eval --gt-mesh` prints)."""
    al = result["alignment"]
    lines = [f"mesh {result['mesh']}  vs  ground truth {result['gt_mesh']}", f"alignment: {al['method']}"]
    if "residual_rms" in al:
        fitted = al.get("cameras_fitted", al["cameras_matched"])
        lines.append(
            f"  {fitted} of {al['cameras_matched']} cameras, residual rms {al['residual_rms']:.4g} ({al['residual_rms_rel']:.3%} "
            f"of the rig radius), max {al['residual_max']:.4g} ({al['worst_camera']})"
        )
        if al.get("cameras_left_out"):
            lines.append("  left out of the fit (more than 3× the median residual: SfM misplaced them): " + ", ".join(
                f"{name} {r:.4g}" for name, r in sorted(al["cameras_left_out"].items(), key=lambda kv: -kv[1])))
    lines.append(
        f"Chamfer-L1 {result['chamfer_l1']:.4g} ({result['chamfer_l1_rel']:.3%} of the GT diagonal {result['gt_diagonal']:.4g}); "
        f"accuracy {result['accuracy']:.4g}, completeness {result['completeness']:.4g}"
    )
    if "normal_consistency" in result:
        lines.append(f"normal agreement (mean |cos| at nearest points, both ways): {result['normal_consistency']:.3f}")
    for tau in result["thresholds"]:
        lines.append(
            f"@{tau:.1%} of diagonal: precision {result[f'precision@{tau:g}']:.3f}  recall {result[f'recall@{tau:g}']:.3f}  "
            f"F-score {result[f'fscore@{tau:g}']:.3f}"
        )
    if "gt_seen_share" in result:
        tau = result["thresholds"][0]
        lines.append(
            f"where the photos can see (the {result['gt_seen_share']:.0%} of the true surface some photo sees, the "
            f"{result['pred_observable_share']:.0%} of the mesh not hidden behind it from every photo): @{tau:.1%} "
            f"precision {result[f'precision_seen@{tau:g}']:.3f}  recall {result[f'recall_seen@{tau:g}']:.3f}  "
            f"F-score {result[f'fscore_seen@{tau:g}']:.3f}")
    if "volume_ratio" in result:
        lines.append(f"volume: {result['volume_ratio']:.3f} of the true solid's (both meshes closed)")
    icp = result.get("icp_refined")
    if icp:
        lines.append(
            f"after ICP refinement (Sim(3), Tanks and Temples' protocol; correction: scale {icp['scale']:.4f}, "
            f"{icp['rotation_deg']:.3f}°, shift {icp['translation_rel']:.3%} of the diagonal): Chamfer-L1 "
            f"{icp['chamfer_l1_rel']:.3%}, normal agreement {icp.get('normal_consistency', float('nan')):.3f}, "
            + ", ".join(f"F@{tau:.1%} {icp[f'fscore@{tau:g}']:.3f}" for tau in result["thresholds"])
        )
    return "\n".join(lines)


MASK_EVAL_SIDE = 800
"""Silhouettes are compared at this longest side (pixels)."""


def silhouette_iou(scene_dir: Path, masks_dir: Path, source: Path | None = None) -> dict[str, Any]:
    """How well the scene's mesh (once meshed) and its masks (if any: the masks it trained with, `masks_*`, or the
    automatic ones normalize was not sure of, `unsure_masks_*`) cut the object out of each photo, against masks the
    user trusts (white = object, same stems as the photos): per photo and mean IoU, precision and recall.

    The mesh is rendered into every photo that has a mask in `masks_dir`, in the normalized frame with the scene's
    cameras; the true masks are undistorted like the photos, so both are pinhole images of the same camera. `source`:
    the input the scene was run on, where masks given with the photos are found."""
    from recon.capture.images import IMAGE_SUFFIXES
    from recon.geometry.raster import mesh_depth

    scene = load_scene(scene_dir / SCENE_FOLDER, source)
    meshed = (scene_dir / MESH_FOLDER / "mesh_report.json").is_file()
    vertices, faces, _ = our_mesh_in_scene_frame(scene_dir) if meshed else (None, None, None)
    truth = {p.stem: p for p in sorted(masks_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES} if masks_dir.is_dir() else {}
    rows: dict[str, dict[str, float]] = {}
    for frame in scene.frames:
        if frame.stem not in truth:
            continue
        scale = min(1.0, MASK_EVAL_SIDE / max(frame.w, frame.h))
        w, h = max(1, round(frame.w * scale)), max(1, round(frame.h * scale))
        true = pinhole_mask(truth[frame.stem], frame, w, h)
        row: dict[str, float] = {}
        if meshed:
            row = _overlap(np.isfinite(mesh_depth(vertices, faces, frame.c2w, frame.intrinsics_at(w, h), (h, w))), true)
        mask = scene.mask_file(frame)
        if mask is not None and mask.is_file():  # the masks the scene trained with
            row.update({f"masks_{k}": v for k, v in _overlap(pinhole_mask(mask, frame, w, h), true).items()})
        unsure = scene_dir / SCENE_FOLDER / UNSURE_MASK_FOLDER / f"{frame.stem}.png"
        if unsure.is_file():  # the automatic masks normalize was not sure enough of to train with
            row.update({f"unsure_masks_{k}": v for k, v in _overlap(pinhole_mask(unsure, frame, w, h), true).items()})
        rows[frame.name] = row
    if not rows:
        raise ReconError(f"No mask in {masks_dir} has the name of a photo of {scene_dir}. Give masks named like the photos.")
    keys = sorted({k for r in rows.values() for k in r})
    if not keys:
        raise ReconError(f"{scene_dir} has neither a mesh nor masks to score: run recon on it first.")
    return {"views": rows, **{f"mean_{k}": float(np.mean([r[k] for r in rows.values() if k in r])) for k in keys},
            **{f"min_{k}": float(min(r[k] for r in rows.values() if k in r)) for k in keys if k.endswith("iou")}}


def _overlap(found: np.ndarray, true: np.ndarray) -> dict[str, float]:
    both = float((found & true).sum())
    return {"iou": both / max(float((found | true).sum()), 1.0), "precision": both / max(float(found.sum()), 1.0),
            "recall": both / max(float(true.sum()), 1.0)}
