"""`recon view`: the viser server starts on a free port, serves its page, shows the scene's objects, renders live.

Where a Chromium is installed, a headless screenshot of the page must not be blank (skipped where absent).
"""
from __future__ import annotations

import socket
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from tests.assets_scene import tiny_scene

viser = pytest.importorskip("viser")

from recon.app.viewer import SceneViewer, render_progressive, viewer_c2w, wxyz  # noqa: E402
from recon.capture.scene import load_scene  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def viewer(tmp_path_factory: pytest.TempPathFactory):
    scene_dir = tiny_scene(tmp_path_factory)[1]
    v = SceneViewer(scene_dir, port=free_port(), device="cpu", log=lambda m: None)
    yield v
    v.stop()


def test_viewer_serves_its_page_on_localhost(viewer: SceneViewer) -> None:
    assert viewer.server.get_host() == "127.0.0.1"
    with urllib.request.urlopen(viewer.url + "/", timeout=10) as response:
        assert response.status == 200
        assert "text/html" in response.headers.get("Content-Type", "")
        assert b"<html" in response.read().lower()


def test_viewer_shows_every_camera_the_points_and_the_mesh(viewer: SceneViewer) -> None:
    import trimesh

    scene = load_scene(viewer.scene_dir / "02_scene")
    assert len(viewer.frustums) == len(scene.frames) == 40
    assert np.allclose(viewer.frustums[3].position, scene.frames[3].center, atol=1e-5)
    assert viewer.points is not None and len(viewer.points.points) == len(scene.points) > 100
    assert viewer.mesh is not None
    ply = trimesh.load(viewer.scene_dir / "04_mesh" / "mesh.ply", process=False)
    assert len(ply.faces) > 100


def test_viewer_camera_conversion_inverts_the_frustum_pose() -> None:
    """A frustum placed with recon's pose, read back as a viser camera, gives the pose again."""
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = q * np.sign(np.linalg.det(q)), rng.normal(size=3)
    back = viewer_c2w(wxyz(c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])), c2w[:3, 3])
    assert np.allclose(back, c2w, atol=1e-12)


def test_progressive_render_matches_a_whole_render_and_cancels(viewer: SceneViewer) -> None:
    field, frame = viewer.field, viewer.scene.frames[0]
    fov = float(2 * np.arctan(0.5 * frame.h / frame.fl_y))
    banded = render_progressive(field, frame.c2w, fov, frame.w / frame.h, 48, lambda: False, band_rays=48 * 5)
    whole = field.render(frame.c2w, 0.5 * 48 / np.tan(0.5 * fov), 48, 48)
    assert banded is not None and np.abs(banded["rgb"] - whole.rgb).max() < 1e-5
    assert banded["rgb"].std() > 0.01  # the object, not only background
    calls = []
    assert render_progressive(field, frame.c2w, fov, 1.0, 48, lambda: calls.append(1) or len(calls) > 2, band_rays=48 * 5) is None
    assert len(calls) == 3  # stopped at the third band boundary


def test_headless_screenshot_is_not_blank(viewer: SceneViewer, tmp_path: Path) -> None:
    """Chromium (software WebGL) opens the page; once the server has sent it a field render, the page is captured."""
    from tests.browser import find_chromium, screenshot

    if find_chromium() is None:
        pytest.skip("no Chromium installed (apt-get install chromium)")
    before = {id(live) for live in viewer.renders.values()}

    def rendered() -> bool:  # this browser's live render has sent its coarse and its second image
        return any(len(live.timings) >= 2 for live in viewer.renders.values() if id(live) not in before)

    shot = screenshot(viewer.url, tmp_path / "shot.png", rendered, timeout_s=180, settle_s=2.0)
    from PIL import Image

    image = np.asarray(Image.open(shot).convert("RGB")).astype(np.float32)
    centre = image[image.shape[0] // 4 : 3 * image.shape[0] // 4, image.shape[1] // 4 : 3 * image.shape[1] // 4]
    assert image.std() > 10
    assert len(np.unique(centre.reshape(-1, 3) // 16, axis=0)) > 50  # the coloured object, not a flat page


def test_browser_cleanup_stops_every_helper_before_removing_the_profile(tmp_path: Path) -> None:
    """Chromium's helpers outlive the browser for a moment and write into its profile: removing it then raced them
    (`OSError: Directory not empty: 'Default'`). A stand-in browser whose helper ignores SIGTERM and keeps writing
    there: the whole process group is stopped and waited for, then the profile removed, without an error."""
    import os
    import subprocess
    import time

    from tests.browser import _group_alive, close_browser

    profile = tmp_path / "profile"
    (profile / "Default").mkdir(parents=True)
    helper = f'trap "" TERM; while :; do touch "{profile}/Default/f$RANDOM"; sleep 0.005; done'
    proc = subprocess.Popen(["bash", "-c", f"bash -c '{helper}' & trap 'exit 0' TERM; wait"], start_new_session=True)
    deadline = time.monotonic() + 30
    while len(os.listdir(profile / "Default")) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert os.listdir(profile / "Default"), "the stand-in helper never wrote"
    close_browser(proc, profile, wait_s=1.0)
    assert proc.returncode is not None and not _group_alive(proc.pid) and not profile.exists()


def test_training_view_shows_progress_and_the_current_render(viewer: SceneViewer) -> None:
    """The `recon run --view` observer: the step/loss/PSNR text, the cameras, and photo | render of a held-out view."""
    from recon.app.viewer import TrainingView
    from recon.evaluation.views import load_views
    from recon.nerf.trainer import TrainProgress

    live = TrainingView(viewer.scene_dir, port=free_port(), interval_s=0.0, side=32)
    try:
        field = viewer.field
        view = load_views(field.scene, field.scene.frames[:1], 64)[0]
        progress = TrainProgress(step=10, steps=30, loss=0.0123, psnr=19.5, lr=1e-2, elapsed_s=1.0, rays_per_s=1000.0)
        data = {"progress": progress, "model": field.model, "view": view, "aabb": field.aabb, "background": field.background}
        live("train_step", data)
        assert "step 10 / 30" in live.text.content and "loss 0.0123" in live.text.content and live.cameras_shown
        image = live._render(data)
        assert image.shape == (32, 64, 3)
        photo, render = image[:, :32].astype(float), image[:, 32:].astype(float)
        assert render.std() > 5 and np.abs(photo - render).mean() < 60  # the object, roughly where the photo has it
    finally:
        live.server.stop()
