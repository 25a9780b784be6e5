"""One tiny trained scene of the shipped sample, built once per test session through `recon.run`.

Shared by the export, API and viewer tests (SfM on 40 photos, 60 training steps, a 48³ mesh), so the
pipeline runs once however many of those tests are selected.
"""
from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest

SAMPLE = Path(__file__).resolve().parents[1] / "fixtures" / "sample"
TINY = {
    "train.steps": 60, "train.batch_rays": 1024, "train.budget": "", "train.eval_every": 0, "train.final_eval_views": 1,
    "train.max_side": 100, "train.checkpoint_every": 0, "mesh.resolution": 48, "mesh.target_faces": 0, "mesh.drop_hidden": False,
    "mesh.texture_size": 64,
    # no culling in these 60 steps of 1,024 rays: the preset's occupancy warm-up (16 steps) is sized for 4,096-ray
    # steps, and a young field culled at step 16 left a mesh of 8 faces once in CI; 30 steps without culling still
    # left one of 8 faces once in the suite (the viewer's test), so the field trains 60
    "train.fast.occupancy_warmup": 60,
}
_BUILT: dict[str, object] = {}


def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, object, float]:
    """(photos folder, scene folder, the RunResult of the first run, its wall time)."""
    if "scene" not in _BUILT:
        import recon

        root = tmp_path_factory.mktemp("assets")
        photos = root / "photos"
        shutil.copytree(SAMPLE / "images", photos)
        t0 = time.perf_counter()
        result = recon.run(photos, out=root / "scene", preset="fast", overrides=TINY)
        _BUILT["scene"] = (photos, root / "scene", result, time.perf_counter() - t0)
    return _BUILT["scene"]  # type: ignore[return-value]
