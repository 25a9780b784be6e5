"""The Python API: `recon.run(...)` runs the pipeline and says what it made; `recon.load_field(...)` renders cameras.

Same runner, presets and caching as the command line (`recon run`), without a console: errors are the
typed `recon.errors` classes (`InputError` for unusable photos or poses, `ConfigError` for a bad preset
or override, `ReconError` for the rest), never an exit code.

    import recon
    result = recon.run("photos/", out="scene/", preset="fast", overrides={"train.steps": 500})
    print(result.metrics["psnr"], result.mesh_files["glb"])
    field = recon.load_field("scene/")
    view = field.render_camera(field.cameras[0].name)   # view.rgb (H, W, 3), view.depth (H, W)
"""
from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from recon.errors import ReconError

if TYPE_CHECKING:
    import numpy as np
    import torch

    from recon.capture.scene import Frame, Scene

STAGE_FOLDERS = {"poses": "01_poses", "normalize": "02_scene", "train": "03_field", "mesh": "04_mesh"}
STAGE_PRODUCTS = {"poses": "camera poses", "normalize": "normalized scene", "train": "trained field", "mesh": "mesh"}


def require_scene(scene_dir: Path, stage: str | None = None) -> None:
    """Raise a `ReconError` that says what to run unless `scene_dir` is a scene folder `recon run` made (and, given
    `stage`, one that stage has written): the commands that read a scene fail on this before they load anything."""
    if not scene_dir.is_dir():
        raise ReconError(f"The scene folder {scene_dir} does not exist. Give the --out folder of a `recon run`, or "
                         f"make one with `recon run PHOTOS --out {scene_dir}`.")
    if not (scene_dir / "manifest.json").is_file():
        raise ReconError(f"{scene_dir} is not a recon scene folder (no manifest.json). Create one with "
                         f"`recon run PHOTOS --out {scene_dir}`.")
    if stage is not None and not (scene_dir / STAGE_FOLDERS[stage]).is_dir():
        raise ReconError(f"{scene_dir} has no {STAGE_PRODUCTS[stage]} yet (no {STAGE_FOLDERS[stage]}/): "
                         f"`recon run PHOTOS --out {scene_dir}` goes on from the stages it has done.")


@dataclass
class StageResult:
    """What one stage did in this run."""

    name: str
    action: str
    """'ran' or 'cached' (its earlier output was still valid)."""
    wall_s: float
    summary: dict[str, Any] = field(default_factory=dict)
    """The stage's own summary (as `recon status` shows it)."""


@dataclass
class RunResult:
    """What `recon.run` made: where it is, what each stage did, and the numbers that say how well."""

    scene: Path
    stages: dict[str, StageResult]
    """Stage name → outcome, in pipeline order (only the stages this run selected)."""
    mesh_files: dict[str, Path]
    """'glb' / 'obj' / 'ply' → path, for the mesh files that exist."""
    metrics: dict[str, Any]
    """From training: held-out 'psnr' (dB), 'ssim', 'steps', 'train_time_s', 'rays_per_s', 'model' (empty before train)."""
    mesh: dict[str, Any]
    """Mesh statistics: 'vertices', 'faces', 'watertight', 'frame' (empty before the mesh stage)."""
    warnings: list[str] = field(default_factory=list)


def run(
    photos: str | Path | None,
    out: str | Path,
    preset: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    *,
    from_stage: str | None = None,
    until_stage: str | None = None,
    force: bool = False,
    verbose: bool = False,
    observers: list[Callable[[str, dict[str, Any]], None]] | None = None,
) -> RunResult:
    """Run the pipeline on `photos` (a photo folder or poses you have) into the scene folder `out`.

    `preset` is a name from `recon presets` or a .toml path; None takes the command line's default
    (`recon.config.DEFAULT_PRESET`). `overrides` are `--set` options as a mapping
    (`{"train.steps": 500, "mesh.frame": "source"}`).
    `photos=None` reuses the source recorded in an existing scene. Finished stages are reused, as on the
    command line. `verbose` prints progress bars and the reasons for each choice; `observers` get live
    events (`("train_step", {...})`, see `recon.stages.train`). Raises `recon.errors.ReconError` (or its
    subclasses `InputError`, `ConfigError`) for anything the caller can fix.
    """
    from rich.console import Console

    from recon.app.progress import Reporter
    from recon.capture.scene import check_source
    from recon.config import DEFAULT_PRESET, load_config
    from recon.stages import default_pipeline

    preset = preset or DEFAULT_PRESET
    scene_dir = Path(out)
    items = [f"{k}={v if isinstance(v, str) else json.dumps(v)}" for k, v in (overrides or {}).items()]
    config = load_config(preset, items)
    report = Reporter(Console(stderr=True, highlight=False), quiet=not verbose)
    report.observers = list(observers or [])
    source = Path(photos).resolve() if photos is not None else None
    if source is not None:
        check_source(source)  # a wrong input (see check_source) is said before the scene folder is made
    outcomes = default_pipeline().run(scene_dir, config, report, source=source, from_stage=from_stage,
                                      until_stage=until_stage, force=force, preset=preset)
    return scene_result(scene_dir, {o.name: StageResult(o.name, o.action, o.wall_s, o.summary) for o in outcomes}, report.warnings)


def scene_result(scene_dir: Path, stages: dict[str, StageResult], warnings: list[str] | None = None) -> RunResult:
    """Collect the files and numbers a scene folder holds (what `run` returns)."""
    metrics: dict[str, Any] = {}
    metrics_path = scene_dir / STAGE_FOLDERS["train"] / "metrics.json"
    if metrics_path.is_file():
        doc = json.loads(metrics_path.read_text())
        metrics = {"psnr": doc["test"]["psnr"], "ssim": doc["test"]["ssim"], "test_views": len(doc["test"]["views"]),
                   **{k: doc[k] for k in ("steps", "train_time_s", "rays_per_s", "model", "device")}}
    mesh_dir = scene_dir / STAGE_FOLDERS["mesh"]
    mesh: dict[str, Any] = {}
    if (mesh_dir / "mesh_report.json").is_file():
        doc = json.loads((mesh_dir / "mesh_report.json").read_text())
        mesh = {"vertices": doc["vertices"], "faces": doc["faces"], "watertight": doc["watertight"],
                "frame": doc["export"]["frame"]}
    return RunResult(scene=scene_dir, stages=stages, mesh_files=mesh_files(scene_dir), metrics=metrics, mesh=mesh,
                     warnings=list(warnings or []))


def mesh_files(scene_dir: Path) -> dict[str, Path]:
    """The scene's vertex-coloured meshes that exist, by format (glb, obj, ply)."""
    mesh_dir = scene_dir / STAGE_FOLDERS["mesh"]
    return {ext: mesh_dir / f"mesh.{ext}" for ext in ("glb", "obj", "ply") if (mesh_dir / f"mesh.{ext}").is_file()}


@dataclass
class Render:
    """One rendered camera: rgb (H, W, 3) float32 in [0, 1], depth (H, W) along the ray (0 where nothing), opacity (H, W)."""

    rgb: np.ndarray
    depth: np.ndarray
    opacity: np.ndarray


class Field:
    """A trained radiance field with its cameras, in recon's normalized scene frame (+Z up).

    Cameras are OpenGL camera-to-world (looks down -Z, +Y up) with pinhole intrinsics in pixels, as in
    `scene.json`.
    """

    def __init__(self, scene: Scene, model: torch.nn.Module, meta: dict[str, Any]):
        import numpy as np
        import torch

        self.scene = scene
        self.model = model
        self.meta = meta
        device = next(model.parameters()).device
        self.aabb = torch.tensor(meta["aabb"], dtype=torch.float32, device=device) if meta.get("bounded", True) else None
        self.background = np.asarray(meta["background"], dtype=np.float32)
        nears = [f.near for f in scene.frames if f.near]
        fars = [f.far for f in scene.frames if f.far]
        self.near_far = (min(nears) if nears else 0.05, max(fars) if fars else 100.0)

    @property
    def cameras(self) -> list[Frame]:
        """Every photo's camera (scene.frames): `.name`, `.c2w`, `.fl_x`…, `.w`, `.h`, `.split`."""
        return self.scene.frames

    def photo_path(self, camera: str | int) -> Path:
        """Where the photo of a camera (by name, stem or index) is: in the folder the scene was last run on."""
        return self.scene.image_path(self._frame(camera))

    def _frame(self, camera: str | int) -> Frame:
        frames = self.scene.frames
        if isinstance(camera, int):
            if not -len(frames) <= camera < len(frames):
                raise ReconError(f"Camera index {camera} is out of range: the scene has {len(frames)} cameras.")
            return frames[camera]
        matches = [f for f in frames if camera in (f.name, f.stem)]
        if not matches:
            raise ReconError(f"No camera named '{camera}' in the scene; names look like '{frames[0].name}'.")
        return matches[0]

    def render(self, c2w: np.ndarray, fl_x: float, width: int, height: int, fl_y: float | None = None,
               cx: float | None = None, cy: float | None = None, chunk: int | None = None) -> Render:
        """Render a pinhole camera: c2w (4, 4) OpenGL camera-to-world; focal and centre in pixels (centre default: the middle)."""
        import numpy as np
        import torch

        from recon.nerf.evaluate import render_image

        if width < 1 or height < 1 or fl_x <= 0:
            raise ReconError(f"A camera needs a positive size and focal length; got {width}×{height}, fl_x={fl_x}.")
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(c2w)):
            raise ReconError(f"c2w must be a finite (4, 4) or (3, 4) camera-to-world matrix; got shape {c2w.shape}.")
        intrinsics = (fl_x, fl_y or fl_x, width / 2 if cx is None else cx, height / 2 if cy is None else cy)
        device = next(self.model.parameters()).device
        bounds: dict[str, Any] = {"aabb": self.aabb} if self.aabb is not None else {"near": self.near_far[0], "far": self.near_far[1]}
        out = render_image(self.model, torch.tensor(c2w, dtype=torch.float32, device=device), intrinsics, height, width,
                           chunk, background=torch.tensor(self.background), **bounds)
        return Render(*(out[k].detach().cpu().numpy() for k in ("rgb", "depth", "opacity")))

    def render_camera(self, camera: str | int, max_side: int | None = None) -> Render:
        """Render one of the photos' cameras (by name, stem or index) at `max_side` (default: the training size)."""
        frame = self._frame(camera)
        side = max_side or self.meta.get("max_side") or max(frame.w, frame.h)
        s = min(1.0, side / max(frame.w, frame.h))
        w, h = max(1, round(frame.w * s)), max(1, round(frame.h * s))
        fl_x, fl_y, cx, cy = frame.intrinsics_at(w, h)
        return self.render(frame.c2w, fl_x, w, h, fl_y, cx, cy)


def load_field(scene: str | Path, device: str = "auto") -> Field:
    """The trained field of a scene folder (made by `recon.run` or `recon run`), ready to render cameras."""
    from recon.capture.scene import load_scene
    from recon.runner.pipeline import recorded_source
    from recon.field import load_field as load_model
    from recon.nerf.device import select_device

    scene_dir = Path(scene)
    if not (scene_dir / STAGE_FOLDERS["normalize"] / "scene.json").is_file():
        raise ReconError(f"{scene_dir} is not a trained recon scene (no {STAGE_FOLDERS['normalize']}/scene.json). "
                         f"Make one with recon.run(photos, out='{scene_dir}').")
    try:
        dev = select_device(device)
    except ValueError as exc:
        raise ReconError(f"device={device}: {exc}") from None
    model, meta = load_model(scene_dir / STAGE_FOLDERS["train"], device=dev)
    return Field(load_scene(scene_dir / STAGE_FOLDERS["normalize"], recorded_source(scene_dir)), model, meta)
