"""An analytic radiance field for the mesh stage's tests: a soft sphere with a direction-dependent colour, photos
of it rendered with the project's renderer, and the mesh stage run on it with no training.

Shared by tests/test_mesh_stage.py and tests/test_geometry_texture.py (test modules never import each other).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torch import Tensor, nn

from recon.app.progress import Reporter
from recon.camera import look_at
from recon.capture.scene import Frame, Scene
from recon.config import MeshConfig, RunConfig
from recon.evaluation.views import View, render_view
from recon.nerf.render import RadianceModel, render_dense
from recon.nerf.sampling import stratified
from recon.runner.pipeline import StageContext
from recon.stages import mesh as mesh_stage

CENTRE = np.array([0.1, -0.05, 0.05])
R0 = 0.6
AABB = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
BACKGROUND = np.ones(3, np.float32)


def sphere_color(x: np.ndarray | Tensor):
    """Analytic albedo: depends only on the direction from the centre, (N, 3) in [0.1, 0.9]."""
    if isinstance(x, Tensor):
        d = x - torch.as_tensor(CENTRE, dtype=x.dtype, device=x.device)
        return 0.5 + 0.4 * d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    d = x - CENTRE
    return 0.5 + 0.4 * d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)


class SoftSphere(RadianceModel):
    """σ = A · sigmoid((R0 − r) / W): iso-surface σ = L at r = R0 − W · logit(L / A) exactly."""

    def __init__(self, amplitude: float, width: float, samples: int = 256) -> None:
        super().__init__()
        self.amplitude, self.width, self.samples = amplitude, width, samples
        self.dummy = nn.Parameter(torch.zeros(()))  # render_view finds the device through parameters()

    def radius_at(self, level: float) -> float:
        p = level / self.amplitude
        return R0 - self.width * math.log(p / (1 - p))

    def density(self, x: Tensor) -> Tensor:
        r = (x - torch.as_tensor(CENTRE, dtype=x.dtype, device=x.device)).norm(dim=-1)
        return self.amplitude * torch.sigmoid((R0 - r) / self.width)

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        return sphere_color(x)

    def render_rays(self, rays_o, rays_d, near, far, *, training, background, colors=True):
        t = stratified(near, far, self.samples, jitter=False)
        x = rays_o[:, None] + t[..., None] * rays_d[:, None]
        sigma = self.density(x.reshape(-1, 3)).view(t.shape)
        rgb = self.radiance(x.reshape(-1, 3), None).view(*t.shape, 3)
        return render_dense(sigma, rgb, t, far, background)


def ring_views(model: SoftSphere, n: int = 8, size: int = 64) -> list[View]:
    """n photos of the analytic field rendered from a ring (two heights) at distance 3; the sphere fills
    ~85 % of the width, a pixel is ~0.023 units at the sphere (the depth test's tolerance is ~0.02)."""
    views = []
    focal = 2.0 * size
    for i in range(n):
        az = 2 * math.pi * (i + 0.3) / n
        el = math.radians(35 if i % 2 else -20)
        eye = 3.0 * np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        blank = View(f"v{i:02d}", np.zeros((size, size, 3), np.uint8), look_at(eye, np.zeros(3)), (focal, focal, size / 2, size / 2), 0.0, 0.0)
        rgb = render_view(model, blank, torch.tensor(AABB, dtype=torch.float32), BACKGROUND)["rgb"]
        blank.image[:] = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
        views.append(blank)
    return views


def write_scene_dir(tmp_path: Path, model: SoftSphere, world_from_source: np.ndarray, kind: str) -> Path:
    """A scene folder with a normalized scene of photos of the analytic field (no 03_field: load_field is patched)."""
    scene_dir = tmp_path / "scene"
    (scene_dir / "02_scene").mkdir(parents=True)
    photos = tmp_path / "photos"
    photos.mkdir()
    frames = []
    for view in ring_views(model, n=6, size=64):
        path = photos / f"{view.name}.png"
        Image.fromarray(view.image).save(path)
        fx, fy, cx, cy = view.intrinsics
        frames.append(Frame(str(path), view.c2w, fx, fy, cx, cy, 64, 64, split="train", near=1.0, far=5.0))
    Scene(frames=frames, aabb=AABB, capture="object", world_from_source=world_from_source, source_kind=kind).save(scene_dir / "02_scene")
    (scene_dir / "manifest.json").write_text(json.dumps({"version": 1, "source": str(photos), "stages": {}}))
    return scene_dir


def run_mesh_stage(scene_dir: Path, model: SoftSphere, cfg: MeshConfig, monkeypatch: pytest.MonkeyPatch) -> tuple[dict, Path]:
    """The mesh stage on `write_scene_dir`'s folder with `model` as the trained field: (its summary, 04_mesh)."""
    meta = {"aabb": AABB.tolist(), "bounded": True, "background": BACKGROUND.tolist(), "max_side": 64, "kind": "analytic"}
    monkeypatch.setattr(mesh_stage, "load_field", lambda folder, device="cpu": (model, meta))
    out = scene_dir / "04_mesh"
    out.mkdir()
    ctx = StageContext(
        name="mesh", folder="04_mesh", out=out, work=scene_dir / ".work", inputs={"normalize": scene_dir / "02_scene", "train": scene_dir / "03_field"},
        config=cfg, run_config=RunConfig(mesh=cfg), source=None, scene_dir=scene_dir, report=Reporter(quiet=True),
    )
    return mesh_stage.run(ctx), out
