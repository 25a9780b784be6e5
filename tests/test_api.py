"""The Python API: `recon.run` returns what it made and raises typed errors; `recon.load_field` renders cameras."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import recon
from recon.evaluation.metrics import psnr
from tests.assets_scene import TINY, tiny_scene


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory):
    return tiny_scene(tmp_path_factory)


def test_import_recon_is_light() -> None:
    """`import recon` must not pull torch or the pipeline (they load on the first call)."""
    out = subprocess.run([sys.executable, "-c", "import sys, recon; print('torch' in sys.modules, 'recon.runner.pipeline' in sys.modules)"],
                         capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[1]).stdout
    assert out.split() == ["False", "False"]
    assert callable(recon.run) and callable(recon.load_field)


def test_run_returns_paths_metrics_and_mesh_stats(built) -> None:
    photos, scene, result, _ = built
    assert isinstance(result, recon.RunResult) and result.scene == scene
    assert list(result.stages) == ["poses", "normalize", "train", "mesh"]
    assert all(s.action == "ran" and s.wall_s > 0 for s in result.stages.values())
    assert result.stages["poses"].summary["registered"] == 40
    assert set(result.mesh_files) == {"glb", "obj", "ply"} and all(p.is_file() for p in result.mesh_files.values())
    assert result.metrics["steps"] == TINY["train.steps"] and 5 < result.metrics["psnr"] < 60
    import trimesh

    ply = trimesh.load(result.mesh_files["ply"], process=False)
    assert result.mesh["faces"] == len(ply.faces) and result.mesh["vertices"] == len(ply.vertices)


def test_second_run_is_cached_and_returns_the_same(built) -> None:
    photos, scene, first, first_s = built
    t0 = time.perf_counter()
    again = recon.run(photos, out=scene, preset="fast", overrides=TINY)
    assert time.perf_counter() - t0 < 0.2 * first_s + 2
    assert all(s.action == "cached" for s in again.stages.values())
    assert again.metrics == first.metrics and again.mesh == first.mesh


def test_typed_errors(tmp_path: Path, built) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(recon.InputError, match="No photos found"):
        recon.run(tmp_path / "empty", out=tmp_path / "s")
    with pytest.raises(recon.ConfigError, match="train.stepz"):
        recon.run(built[0], out=tmp_path / "s2", overrides={"train.stepz": 3})
    with pytest.raises(recon.InputError, match="does not exist"):
        recon.run(tmp_path / "typo", out=tmp_path / "s3")
    assert not (tmp_path / "s3").exists()  # refused before the scene folder is made
    with pytest.raises(recon.ReconError, match="not a trained recon scene"):
        recon.load_field(tmp_path)
    assert issubclass(recon.InputError, recon.ReconError) and issubclass(recon.ConfigError, recon.ReconError)


def test_load_field_renders_a_photo_camera_like_the_train_stage(built) -> None:
    """The held-out render through the API scores the PSNR the train stage recorded for the same view."""
    import json

    from recon.capture.images import read_image, undistort

    scene = built[1]
    field = recon.load_field(scene, device="cpu")
    recorded = json.loads((scene / "03_field" / "metrics.json").read_text())["test"]["views"][0]
    frame = next(f for f in field.cameras if f.stem == recorded["view"])
    view = field.render_camera(frame.stem)
    h, w = view.rgb.shape[:2]
    assert max(h, w) == TINY["train.max_side"] and view.depth.shape == (h, w) and view.opacity.shape == (h, w)
    photo = read_image(field.photo_path(frame.stem), max_side=TINY["train.max_side"])[..., :3]
    photo = undistort(photo, frame.fl_x * w / frame.w, frame.fl_y * h / frame.h, frame.cx * w / frame.w, frame.cy * h / frame.h, frame.distortion)
    import torch

    assert float(psnr(torch.from_numpy(view.rgb), torch.from_numpy(photo))) == pytest.approx(recorded["psnr"], abs=0.01)
    hit = view.opacity > 0.5
    distance = np.linalg.norm(frame.center - np.asarray(field.meta["aabb"]).mean(0))
    assert hit.any() and np.all(np.abs(view.depth[hit] - distance) < 0.75 * distance)
