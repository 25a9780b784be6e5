"""The end of `recon run`: where the mesh's files are and how to open them."""
from __future__ import annotations

from pathlib import Path

from PIL import Image
from typer.testing import CliRunner

from recon.app import cli
from recon.app.cli import app, mesh_deliverables
from recon.config import DEFAULT_PRESET, load_config
from recon.runner.pipeline import StageOutcome


def _mesh_folder(scene: Path, names: list[str]) -> Path:
    folder = scene / "04_mesh"
    folder.mkdir(parents=True)
    for name in names:
        (folder / name).write_bytes(b"x")
    return folder


def test_deliverables_name_the_files_that_exist(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    folder = _mesh_folder(scene, ["mesh.glb", "mesh_textured.glb", "mesh.obj", "mesh.ply", "preview_front.png"])
    text = "\n".join(mesh_deliverables(scene))
    assert str(folder / "mesh.glb") in text and "Blender" in text
    assert str(folder / "mesh_textured.glb") in text
    assert "mesh.obj and mesh.ply" in text
    assert "preview_front.png" in text and "preview_side.png" not in text
    assert f"recon view {scene}" in text


def test_deliverables_leave_out_a_textured_copy_that_failed(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    _mesh_folder(scene, ["mesh.glb", "mesh.ply"])
    text = "\n".join(mesh_deliverables(scene))
    assert "mesh_textured" not in text and "mesh.obj" not in text
    assert "mesh.ply beside them" in text


def test_no_mesh_no_deliverables(tmp_path: Path) -> None:
    assert mesh_deliverables(tmp_path / "scene") == []
    _mesh_folder(tmp_path / "other", ["mesh.ply"])  # a stage cut short before its glb
    assert mesh_deliverables(tmp_path / "other") == []


class _Pipeline:
    """Stands in for the stages: reports what a run did without running anything."""

    def __init__(self, names: list[str]) -> None:
        self.names = names

    def run(self, scene_dir: Path, *args, **kwargs) -> list[StageOutcome]:
        return [StageOutcome(name, "cached", 0.0, {"headline": f"{name} done"}) for name in self.names]


def test_a_run_ends_with_where_its_mesh_is_unless_it_stopped_before_the_mesh(tmp_path: Path, monkeypatch) -> None:
    scene = tmp_path / "scene"
    _mesh_folder(scene, ["mesh.glb", "mesh.obj", "mesh.ply"])  # a mesh from an earlier run
    runner = CliRunner()
    monkeypatch.setattr(cli, "_pipeline", lambda: _Pipeline(["poses", "normalize", "train", "mesh"]))
    result = runner.invoke(app, ["mesh", str(scene)])
    assert result.exit_code == 0, result.output
    assert "your mesh:" in result.output and "mesh.glb" in result.output
    monkeypatch.setattr(cli, "_pipeline", lambda: _Pipeline(["poses"]))  # --until poses: the old mesh is not this run's
    result = runner.invoke(app, ["poses", str(scene)])
    assert result.exit_code == 0, result.output
    assert "your mesh" not in result.output


class _Recording(_Pipeline):
    """A stand-in that keeps the configuration and preset name the run was given."""

    def run(self, scene_dir: Path, config, *args, **kwargs) -> list[StageOutcome]:
        self.config, self.preset = config, kwargs.get("preset")
        return super().run(scene_dir)


def test_a_run_without_a_preset_takes_the_default_and_says_why(tmp_path: Path, monkeypatch) -> None:
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a", "b", "c"):  # a folder with fewer than three photos is refused before the pipeline
        Image.new("RGB", (40, 40)).save(photos / f"{name}.png")
    pipeline = _Recording(["poses", "normalize", "train", "mesh"])
    monkeypatch.setattr(cli, "_pipeline", lambda: pipeline)
    result = CliRunner().invoke(app, ["run", str(photos), "--out", str(tmp_path / "scene")])
    assert result.exit_code == 0, result.output
    assert pipeline.preset == DEFAULT_PRESET and pipeline.config.train == load_config(DEFAULT_PRESET).train
    said = " ".join(result.output.split())
    assert f"preset {DEFAULT_PRESET} (the default:" in said and "--preset NAME picks another" in said
    result = CliRunner().invoke(app, ["run", str(photos), "--out", str(tmp_path / "scene2"), "--preset", "balanced"])
    assert result.exit_code == 0, result.output
    assert pipeline.preset == "balanced" and pipeline.config.train.budget == "10m"
    assert "the default:" not in result.output



def test_batch_says_which_preset_it_took_and_why(tmp_path: Path, monkeypatch) -> None:
    """`recon batch` without --preset starts with the same line as `recon run`: the default and why."""
    seen: list = []

    def run_batch(inputs, out: Path, preset: str, *args, **kwargs) -> dict:
        seen.append(preset)
        out.mkdir()
        (out / "batch.md").write_text("# batch")
        return {"failed": 0, "captures": []}

    monkeypatch.setattr("recon.app.batch.run_batch", run_batch)
    result = CliRunner().invoke(app, ["batch", str(tmp_path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert seen == [DEFAULT_PRESET] and f"preset {DEFAULT_PRESET} (the default:" in said
    assert "the default:" not in cli.preset_line("balanced") and "balanced" in cli.preset_line("balanced")


def test_presets_marks_the_default() -> None:
    result = CliRunner().invoke(app, ["presets"])
    assert result.exit_code == 0, result.output
    marked = [line.split(":")[0] for line in result.output.splitlines() if "(default)" in line.split(":")[0]]
    assert marked == [f"{DEFAULT_PRESET} (default)"]
