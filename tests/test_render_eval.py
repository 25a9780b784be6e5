"""`recon render` and `recon eval` on a tiny trained scene: files named after the photos, videos, metrics."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from recon.app.cli import app
from tests import faults

runner = CliRunner()


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("render")
    capture = faults.make_capture(root / "capture")
    proc = faults.run(capture, root / "scene", "--until", "train")
    assert proc.returncode == 0, proc.stderr
    return root / "scene"


def invoke(*args: str) -> str:
    result = runner.invoke(app, list(args))
    assert result.exit_code == 0, result.output
    return result.output


def test_orbit_render_writes_frames_and_videos(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "orbit"
    invoke("render", str(trained), "--out", str(out), "--path", "orbit", "--frames", "3", "--depth")
    assert sorted(p.name for p in out.glob("orbit_00?.png")) == ["orbit_000.png", "orbit_001.png", "orbit_002.png"]
    assert (out / "orbit.gif").stat().st_size > 0 and (out / "orbit_depth.gif").is_file()


def test_test_path_frames_are_named_after_the_photos(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "test"
    invoke("render", str(trained), "--out", str(out), "--path", "test")
    scene = json.loads((trained / "02_scene" / "scene.json").read_text())
    stems = {Path(f["file_path"]).stem for f in scene["frames"] if f.get("split") == "test"}
    stems = stems or {Path(f["file_path"]).stem for f in scene["frames"]}  # tiny captures hold nothing out
    assert stems == {p.stem for p in out.glob("*.png")}


def test_eval_writes_per_view_metrics_and_a_grid(trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    text = invoke("eval", str(trained), "--out", str(out), "--split", "train", "--limit", "2")
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["views"]) == 2 and metrics["psnr"] > 5 and 0 < metrics["ssim"] <= 1
    assert (out / "grid.png").is_file() and "mean PSNR" in text


def test_bad_render_path_is_a_clear_error(trained: Path, tmp_path: Path) -> None:
    result = runner.invoke(app, ["render", str(trained), "--out", str(tmp_path / "x"), "--path", "helix"])
    assert result.exit_code == 2 and "orbit, spiral, train or test" in result.output
