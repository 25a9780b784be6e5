"""Renders of a trained scene: camera paths (orbit, spiral, the photos' own), videos, and evaluation.

Used by `recon render` and `recon eval`; the train stage's own held-out evaluation uses the same
`evaluate` so the numbers agree.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from recon.atomic import write_json_atomic
from recon.camera import look_at
from recon.capture.images import save_image
from recon.capture.scene import Scene, load_scene, spread_evenly
from recon.errors import ReconError
from recon.evaluation.views import (
    View,
    evaluate,
    fitted_note,
    load_views,
    render_view,
    supersampling_note,
    training_focal,
    write_previews,
)
from recon.field import load_field
from recon.runner.ownership import OwnedFolder, claim_folder, claim_names
from recon.runner.pipeline import recorded_source

PathKind = Literal["orbit", "spiral", "train", "test"]


def orbit_poses(scene: Scene, n: int, spiral: bool = False) -> list[np.ndarray]:
    """Cameras circling the box centre at the photos' median distance and elevation (spiral: elevation swings)."""
    centre = np.asarray(scene.aabb).mean(axis=0)
    offsets = np.stack([f.c2w[:3, 3] for f in scene.frames]) - centre
    radius = float(np.median(np.linalg.norm(offsets, axis=1)))
    elevation = float(np.median(np.arcsin(np.clip(offsets[:, 2] / np.linalg.norm(offsets, axis=1), -1, 1))))
    poses = []
    for i in range(n):
        az = 2 * np.pi * i / n
        el = elevation + (np.radians(15) * np.sin(2 * az) if spiral else 0.0)
        eye = centre + radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        poses.append(look_at(eye, centre))
    return poses


def _write_video(frames: list[np.ndarray], out: Path, fps: int) -> list[Path]:
    """An animated GIF always (Pillow), and an MP4 when OpenCV's writer is available."""
    from PIL import Image

    written = []
    pil = [Image.fromarray((np.clip(f, 0, 1) * 255).astype(np.uint8)) for f in frames]
    gif = out.with_suffix(".gif")
    pil[0].save(gif, save_all=True, append_images=pil[1:], duration=int(1000 / fps), loop=0)
    written.append(gif)
    try:
        import cv2
    except ImportError:
        return written
    try:
        h, w = frames[0].shape[:2]
        mp4 = out.with_suffix(".mp4")
        writer = cv2.VideoWriter(str(mp4), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if writer.isOpened():
            for f in frames:
                writer.write(cv2.cvtColor((np.clip(f, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
            writer.release()
            written.append(mp4)
    except (cv2.error, OSError):  # no codec on this machine: the GIF is enough
        return written
    return written


def _trained(scene_dir: Path, device: str) -> tuple[Scene, torch.nn.Module, dict[str, Any], torch.Tensor | None]:
    from recon.nerf.device import select_device

    scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
    model, meta = load_field(scene_dir / "03_field", device=select_device(device))
    aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=next(model.parameters()).device) if meta.get("bounded", True) else None
    return scene, model, meta, aabb


def render_names(scene: Scene, kind: PathKind, frames: int, depth: bool) -> list[str]:
    """The files a render of this path writes (frames, then videos), known before anything renders."""
    stems = [f.stem for f in (scene.split(kind) or scene.frames)] if kind in ("train", "test") else [f"{kind}_{i:03d}" for i in range(frames)]
    videos = [kind, f"{kind}_depth"] if depth else [kind]
    return ([f"{s}.png" for s in stems] + ([f"{s}_depth.png" for s in stems] if depth else [])
            + [f"{v}{ext}" for v in videos for ext in (".gif", ".mp4")])


def render_path(scene_dir: Path, kind: PathKind, out_dir: Path, frames: int = 60, max_side: int | None = None,
                depth: bool = False, fps: int = 24, device: str = "auto", report: Any = None) -> list[Path]:
    """Render a camera path to PNG frames + GIF/MP4. train/test frames are named after their photos.

    `out_dir` follows recon's ownership rule (`recon.runner.ownership`): a new or empty folder or an earlier render,
    whose files recon replaces while a file of the user's in the way is refused before anything renders.
    """
    from recon.plots import depth_to_color
    from recon.stages import scene_parts

    owned = claim_folder(out_dir, "render", scene_parts)
    owned.check_free(render_names(load_scene(scene_dir / "02_scene", recorded_source(scene_dir)), kind, frames, depth))
    scene, model, meta, aabb = _trained(scene_dir, device)
    background = np.asarray(meta["background"], dtype=np.float32)
    side = max_side or meta["max_side"]
    if kind in ("train", "test"):
        split = scene.split(kind) or scene.frames
        views = load_views(scene, split, side)
    else:
        ref = load_views(scene, scene.frames[:1], side)[0]
        views = [View(f"{kind}_{i:03d}", ref.image, pose, ref.intrinsics, ref.near, ref.far) for i, pose in enumerate(orbit_poses(scene, frames, kind == "spiral"))]
    rgb_frames, depth_frames = [], []
    with owned.staging() as staged:
        task = report.task(f"rendering {kind} path", total=len(views)) if report else None
        bar = task.__enter__() if task else None
        try:
            for view in views:
                out = render_view(model, view, aabb, background)
                save_image(staged / f"{view.name}.png", out["rgb"])
                rgb_frames.append(out["rgb"])
                if depth:
                    d = depth_to_color(out["depth"], out["opacity"])
                    save_image(staged / f"{view.name}_depth.png", d)
                    depth_frames.append(d)
                if bar:
                    bar.advance()
        finally:
            if task:
                task.__exit__(None, None, None)
        written = _write_video(rgb_frames, staged / kind, fps)
        if depth_frames:
            written += _write_video(depth_frames, staged / f"{kind}_depth", fps)
        owned.replace_with(staged)
    return [out_dir / p.name for p in written]


EVAL_FILES = ("metrics.json", "grid.png", "silhouette_iou.json", "mesh_accuracy.json")
"""What `recon eval` writes at the top of its folder (SCENE/eval or --out), beside views/<photo>.png."""


def claim_eval_folder(out_dir: Path, names: list[str]) -> OwnedFolder:
    """Check that `recon eval` may write `names` into `out_dir` (recon.runner.ownership), before it renders: a new or
    empty folder or an earlier evaluation's, where a file of the user's in the way is refused, never replaced."""
    from recon.stages import scene_parts

    return claim_names(out_dir, "eval", scene_parts, names, _unrecorded_eval)


def _unrecorded_eval(folder: Path) -> list[str] | None:
    """The files of an evaluation folder without a record, when it holds only what `recon eval` writes and one of its
    JSON files is recon's (per-view rows or a mesh comparison)."""
    from recon.atomic import read_json

    def ours(name: str) -> bool:
        try:
            doc = read_json(folder / name)
        except (OSError, ValueError):
            return False
        return isinstance(doc, dict) and ("views" in doc or "chamfer_l1_rel" in doc)

    files = [p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir()]
    if (any(ours(n) for n in EVAL_FILES if n.endswith(".json") and n in files)
            and all(n in EVAL_FILES or n.startswith("views/") and n.count("/") == 1 and n.endswith(".png")
                    and not (folder / n).is_symlink() for n in files)):
        return files
    return None


def evaluate_scene(scene_dir: Path, out_dir: Path, split: str = "test", max_side: int | None = None, device: str = "auto", report: Any = None, limit: int = 0) -> dict[str, Any]:
    """Render every view of a split: per-view and mean PSNR/SSIM (metrics.json) and an image grid PNG."""
    scene, model, meta, aabb = _trained(scene_dir, device)
    frames = scene.split(split)
    frames = spread_evenly(frames, limit)  # the same views training's final evaluation picks (limit 0: all)
    if not frames:
        raise ReconError(f"The scene has no '{split}' views to evaluate. Try --split val or --split train.")
    background = np.asarray(meta["background"], dtype=np.float32)
    views = load_views(scene, frames, max_side or meta["max_side"], report, f"{split} photos")
    focal = training_focal(scene.split("train") or frames, meta["max_side"])
    note = supersampling_note(views, focal)
    if note and report:
        report.info(note)
    claim_eval_folder(out_dir, ["metrics.json", "grid.png", *(f"views/{v.name}.png" for v in views)])
    appearance = bool(meta.get("appearance"))  # trained with per-photo appearance: the left-half / right-half protocol
    if report:
        with report.task(f"rendering the {split} views", total=len(views), unit="views") as bar:
            result = evaluate(model, views, aabb, background, keep=True, appearance=appearance, focal=focal,
                              on_view=bar.advance)
    else:
        result = evaluate(model, views, aabb, background, keep=True, appearance=appearance, focal=focal)
    if report and (fitted := fitted_note(result)):
        report.info(fitted)
    renders = result.pop("renders")
    write_previews(renders, out_dir / "views")
    _grid([r[1]["rgb"] for r in renders], [r[2] for r in renders], out_dir / "grid.png")
    result["split"] = split
    write_json_atomic(out_dir / "metrics.json", result)
    return result


def _grid(renders: list[np.ndarray], photos: list[np.ndarray], path: Path, max_tiles: int = 8) -> None:
    """Top row photos, bottom row renders, up to `max_tiles` views."""
    n = min(len(renders), max_tiles)
    h, w = renders[0].shape[:2]
    grid = np.ones((2 * h + 4, n * (w + 4) - 4, 3), dtype=np.float32)
    for i in range(n):
        x = i * (w + 4)
        grid[:h, x : x + w] = photos[i][:h, :w, :3]
        grid[h + 4 :, x : x + w] = renders[i][:h, :w]
    save_image(path, grid)
