"""`recon view SCENE`: a local web viewer (viser) of the cameras, sparse points, mesh and the live field.

The field is rendered from the browser's camera on a background thread, progressively — a coarse image
first (a fraction of a second on a CPU), then sharper ones — and a camera move cancels the render in
progress between row bands, so the viewer stays interactive. `TrainingView` is the observer behind
`recon run --view`: it shows the loss, PSNR and the current render of a held-out photo while training runs.

viser is an optional dependency (`pip install -e ".[view]"`); without it the commands say how to install it.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from recon.app.api import require_scene
from recon.camera import flip_camera_axes
from recon.errors import ReconError
from recon.runner.pipeline import recorded_source

if TYPE_CHECKING:
    import viser

    from recon.app.api import Field
    from recon.capture.scene import Scene

LEVELS = (64, 160)
"""Long sides of the progressive renders before the final one (pixels)."""
PHOTO_SIDE = 128
"""Long side of the photos shown in the camera frustums."""


def require_viser() -> Any:
    """The viser module, or a ReconError that says how to install it."""
    try:
        import viser
    except ImportError:
        raise ReconError(
            'The viewer needs the optional package viser. Install it with: pip install -c constraints.txt -e ".[view]"'
        ) from None
    return viser


def wxyz(rotation: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) of a (3, 3) rotation."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def viewer_c2w(wxyz_: np.ndarray, position: np.ndarray) -> np.ndarray:
    """recon's (4, 4) OpenGL camera-to-world from a viser camera (OpenCV axes, quaternion w x y z)."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = np.asarray(wxyz_, np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = flip_camera_axes(Rotation.from_quat([x, y, z, w]).as_matrix())
    c2w[:3, 3] = position
    return c2w


def render_progressive(field: Field, c2w: np.ndarray, fov_y: float, aspect: float, side: int,
                       cancelled: Callable[[], bool], band_rays: int = 8192) -> dict[str, np.ndarray] | None:
    """Render a (fov_y, aspect) camera at long side `side` in row bands; None as soon as `cancelled()` is true.

    Returns rgb (H, W, 3) and depth (H, W).
    """
    w, h = (side, max(1, round(side / aspect))) if aspect >= 1 else (max(1, round(side * aspect)), side)
    focal = 0.5 * h / np.tan(0.5 * fov_y)
    rows = max(1, band_rays // w)
    rgb = np.zeros((h, w, 3), np.float32)
    depth = np.zeros((h, w), np.float32)
    for r0 in range(0, h, rows):
        if cancelled():
            return None
        r1 = min(h, r0 + rows)
        out = field.render(c2w, focal, w, r1 - r0, fl_y=focal, cx=w / 2, cy=h / 2 - r0)
        rgb[r0:r1], depth[r0:r1] = out.rgb, out.depth
    return {"rgb": rgb, "depth": depth}


def depth_image(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) → an RGB image (near bright), using recon's depth colours."""
    from recon.plots import depth_to_color

    return depth_to_color(depth, (depth > 0).astype(np.float32))


class LiveRender:
    """One browser's live field render: a background thread, restarted (cancelling the current one) on each camera move."""

    def __init__(self, client: Any, field: Field, settings: Callable[[], dict[str, Any]], log: Callable[[str], None] = print):
        self.client, self.field, self.settings, self.log = client, field, settings, log
        self.version = 0
        self.stopped = False
        self.cond = threading.Condition()
        self.timings: list[tuple[int, float]] = []
        """(long side, seconds) of each finished render, for `recon view`'s log and the tests."""
        self.thread = threading.Thread(target=self._loop, name="recon-live-render", daemon=True)
        self.thread.start()

    def request(self) -> None:
        with self.cond:
            self.version += 1
            self.cond.notify()

    def stop(self, wait_s: float = 30.0) -> None:
        """Cancel and wait for the thread (a render stops at its next band): torch must not be mid-op at exit."""
        with self.cond:
            self.stopped = True
            self.cond.notify()
        if threading.current_thread() is not self.thread:
            self.thread.join(wait_s)

    def _loop(self) -> None:
        done = 0
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.stopped or self.version != done)
                if self.stopped:
                    return
                version = done = self.version
            try:
                self._render(version)
            except Exception as exc:  # a client that left mid-render: nothing to show it any more
                if not self.stopped:
                    self.log(f"live render stopped ({type(exc).__name__}: {exc})")
                return

    def _render(self, version: int) -> None:
        settings = self.settings()
        if settings["mode"] == "mesh":
            self.client.scene.set_background_image(None)
            return
        cam = self.client.camera
        c2w, fov, aspect = viewer_c2w(cam.wxyz, cam.position), float(cam.fov), float(cam.aspect)
        for side in [s for s in LEVELS if s < settings["max_side"]] + [settings["max_side"]]:
            t0 = time.perf_counter()
            out = render_progressive(self.field, c2w, fov, aspect, side, lambda: self.stopped or self.version != version)
            if out is None:
                return
            self.timings.append((side, time.perf_counter() - t0))
            image = depth_image(out["depth"]) if settings["mode"] == "depth" else out["rgb"]
            self.client.scene.set_background_image((np.clip(image, 0, 1) * 255).astype(np.uint8), format="jpeg")


class SceneViewer:
    """The viser scene of a recon scene folder: frustums with photos, sparse points, the mesh, the live field.

    Handles are kept (`frustums`, `points`, `mesh`) so callers and tests can see what was shown.
    """

    def __init__(self, scene_dir: Path, host: str = "127.0.0.1", port: int = 8080, server: viser.ViserServer | None = None,
                 device: str = "auto", log: Callable[[str], None] = print):
        from recon.capture.scene import load_scene

        viser = require_viser()
        self.scene_dir = scene_dir
        require_scene(scene_dir, "normalize")
        self.scene: Scene = load_scene(scene_dir / "02_scene", recorded_source(scene_dir))
        self.log = log
        self.server = server or viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        self.frustums = add_cameras(self.server, self.scene)
        self.points = add_points(self.server, self.scene)
        self.field = self._load_field(device)
        self.mesh = self._add_mesh()
        self.renders: dict[int, LiveRender] = {}
        gui = self.server.gui
        modes = ("field", "depth", "mesh") if self.field is not None else ("mesh",)
        self.mode = gui.add_dropdown("Show", modes, initial_value=modes[0])
        if self.mesh is not None:
            self.mesh.visible = self.mode.value == "mesh"
        side = int(self.field.meta.get("max_side", 400)) if self.field is not None else 400
        self.max_side = gui.add_slider("Render size", min=64, max=1024, step=16, initial_value=min(side, 512))
        self.show_cameras = gui.add_checkbox("Cameras", initial_value=True)
        self.mode.on_update(lambda _: self._changed())
        self.max_side.on_update(lambda _: self._changed())
        self.show_cameras.on_update(lambda _: self._toggle_cameras())
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _add_mesh(self) -> Any:
        """04_mesh/mesh.ply, mapped back into the normalized frame (the mesh stage may have exported it in another)."""
        import json

        import trimesh

        mesh_dir = self.scene_dir / "04_mesh"
        if not (mesh_dir / "mesh.ply").is_file():
            self.log("no mesh yet (04_mesh/mesh.ply): showing cameras, points and the field")
            return None
        mesh = trimesh.load(mesh_dir / "mesh.ply", process=False)
        report = json.loads((mesh_dir / "mesh_report.json").read_text())
        mesh.apply_transform(np.linalg.inv(np.asarray(report["export"]["transform"], np.float64)))
        return self.server.scene.add_mesh_trimesh("/mesh", mesh)  # shown when "Show" is "mesh"

    def _load_field(self, device: str) -> Field | None:
        if not (self.scene_dir / "03_field" / "field.pt").is_file():
            self.log("no trained field yet (03_field/field.pt): no live render")
            return None
        from recon.app.api import load_field

        return load_field(self.scene_dir, device=device)

    def _settings(self) -> dict[str, Any]:
        return {"mode": self.mode.value, "max_side": int(self.max_side.value)}

    def _changed(self) -> None:
        if self.mesh is not None:
            self.mesh.visible = self.mode.value == "mesh"
        for live in self.renders.values():
            live.request()

    def _toggle_cameras(self) -> None:
        for handle in self.frustums:
            handle.visible = self.show_cameras.value

    def _connect(self, client: Any) -> None:
        frame = self.scene.frames[0]
        target = np.asarray(self.scene.aabb).mean(axis=0) if self.scene.aabb is not None else np.zeros(3)
        client.camera.fov = float(2 * np.arctan(0.5 * frame.h / frame.fl_y))
        # start between the first photo and its nearest neighbour, a little farther out: no frustum in the way
        offsets = np.stack([f.center for f in self.scene.frames]) - target
        nearest = np.argsort(np.linalg.norm(offsets - offsets[0], axis=1))[1] if len(offsets) > 1 else 0
        radius = float(np.linalg.norm(offsets[0]))
        client.camera.position = target + 1.15 * radius * _unit(_unit(offsets[0]) + _unit(offsets[nearest]))
        client.camera.look_at = target
        client.camera.up_direction = (0.0, 0.0, 1.0)
        if self.field is None:
            return
        live = LiveRender(client, self.field, self._settings, self.log)
        self.renders[client.client_id] = live
        client.camera.on_update(lambda _: live.request())
        live.request()

    def _disconnect(self, client: Any) -> None:
        live = self.renders.get(client.client_id)
        if live is not None:
            live.stop(wait_s=0.0)  # joined in stop()

    def stop(self) -> None:
        for live in list(self.renders.values()):
            live.stop()
        self.server.stop()


def add_cameras(server: viser.ViserServer, scene: Scene) -> list[Any]:
    """A frustum per photo, with the photo (downscaled) on it; train/val/test cameras coloured apart."""
    from recon.capture.images import read_image

    colors = {"train": (40, 40, 40), "val": (40, 120, 220), "test": (220, 60, 40)}
    extent = float(np.ptp(np.asarray(scene.aabb), axis=0).max()) if scene.aabb is not None else 1.0
    handles = []
    for i, f in enumerate(scene.frames):
        try:
            photo = (np.clip(read_image(scene.image_path(f), max_side=PHOTO_SIDE)[..., :3], 0, 1) * 255).astype(np.uint8)
        except Exception:  # a missing photo still has a camera worth showing
            photo = None
        handles.append(server.scene.add_camera_frustum(
            f"/cameras/{i:04d}", fov=float(2 * np.arctan(0.5 * f.h / f.fl_y)), aspect=f.w / f.h, scale=0.08 * extent,
            color=colors.get(f.split or "train", colors["train"]), image=photo,
            wxyz=wxyz(flip_camera_axes(f.c2w[:3, :3])), position=f.center,
        ))
    return handles


def add_points(server: viser.ViserServer, scene: Scene) -> Any:
    """The sparse SfM points with their colours (None when the poses were imported without points)."""
    if not len(scene.points):
        return None
    extent = float(np.ptp(scene.points, axis=0).max())
    return server.scene.add_point_cloud("/points", np.asarray(scene.points, np.float32),
                                        np.asarray(scene.point_colors, np.uint8), point_size=0.004 * extent)


class TrainingView:
    """Observer for `recon run --view`: loss, PSNR and the current render of a held-out photo, live.

    Renders on the training thread (so the model is never read mid-update), at most every
    `interval_s` seconds and at `side` pixels, which keeps the cost to a few percent of training.
    """

    def __init__(self, scene_dir: Path, host: str = "127.0.0.1", port: int = 8080, interval_s: float = 5.0, side: int = 128):
        viser = require_viser()
        self.scene_dir, self.interval_s, self.side = scene_dir, interval_s, side
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        self.text = self.server.gui.add_markdown("**recon** — waiting for training to start…")
        self.image = self.server.gui.add_image(np.zeros((side, 2 * side, 3), np.uint8), label="photo | current render")
        self.last = -np.inf
        self.cameras_shown = False
        self.render_s: list[float] = []

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def __call__(self, event: str, data: dict[str, Any]) -> None:
        if event != "train_step":
            return
        p = data["progress"]
        now = time.perf_counter()
        if now - self.last < self.interval_s and p.step != p.steps:
            return
        self.last = now
        if not self.cameras_shown:
            from recon.capture.scene import load_scene

            scene = load_scene(self.scene_dir / "02_scene", recorded_source(self.scene_dir))
            add_cameras(self.server, scene)
            add_points(self.server, scene)
            self.cameras_shown = True
        evals = f", held-out PSNR {p.metrics['psnr']:.2f} dB" if p.metrics else ""
        self.text.content = (f"**training** step {p.step:,} / {p.steps:,} — loss {p.loss:.4f}, batch PSNR {p.psnr:.2f} dB{evals}, "
                             f"{p.rays_per_s:,.0f} rays/s")
        if self.server.get_clients():
            self.image.image = self._render(data)

    def _render(self, data: dict[str, Any]) -> np.ndarray:
        import torch

        from recon.capture.images import resize
        from recon.nerf.evaluate import render_image

        t0 = time.perf_counter()
        view, model = data["view"], data["model"]
        h, w = view.hw
        s = self.side / max(h, w)
        rw, rh = max(1, round(w * s)), max(1, round(h * s))
        fx, fy, cx, cy = view.intrinsics
        device = next(model.parameters()).device
        bounds = {"aabb": data["aabb"]} if data["aabb"] is not None else {"near": view.near, "far": view.far}
        out = render_image(model, torch.tensor(view.c2w, dtype=torch.float32, device=device), (fx * s, fy * s, cx * s, cy * s),
                           rh, rw, background=torch.tensor(data["background"]), **bounds)
        photo = resize(view.image[..., :3].astype(np.float32) / 255.0, (rw, rh))
        self.render_s.append(time.perf_counter() - t0)
        return (np.clip(np.concatenate([photo, out["rgb"].cpu().numpy()], axis=1), 0, 1) * 255).astype(np.uint8)
