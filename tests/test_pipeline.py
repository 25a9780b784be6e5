"""The stage runner: caching by fingerprint, re-runs on change, atomic folders, checksums, lock."""
from __future__ import annotations

import fcntl
import json
import multiprocessing
import os
import shutil
import threading
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from typer.testing import CliRunner

from recon.app.cli import app
from recon.app.progress import Reporter
from recon.config import RunConfig
from recon.errors import ReconError
from recon.runner.pipeline import Manifest, Pipeline, Stage, StageContext, running_pid, scene_lock

CALLS: list[str] = []


@dataclass
class _A:
    value: int = 1


@dataclass
class _B:
    factor: int = 2


@dataclass
class _Config(RunConfig):
    a: _A = field(default_factory=_A)
    b: _B = field(default_factory=_B)


def _digest_source(source: Path, cfg: object) -> str:  # by name, as the poses stage's: the same photos may move
    return "|".join(f"{p.name}:{p.read_text()}" for p in sorted(source.iterdir()))


def _stage_a(ctx: StageContext) -> dict:
    CALLS.append("a")
    total = sum(int(p.read_text()) for p in sorted(ctx.source.iterdir()))
    (ctx.out / "a.txt").write_text(str(total * ctx.config.value))
    return {"total": total}


def _stage_b(ctx: StageContext) -> dict:
    CALLS.append("b")
    a = int((ctx.inputs["a"] / "a.txt").read_text())
    (ctx.out / "b.txt").write_text(str(a * ctx.config.factor))
    if os.environ.get("RECON_TEST_FAIL_B"):
        raise RuntimeError("boom")
    return {"b": a * ctx.config.factor}


PIPE = Pipeline(
    [
        Stage("a", "01_a", (), 1, _stage_a, needs_source=True, source_digest=_digest_source),
        Stage("b", "02_b", ("a",), 1, _stage_b),
    ]
)


@pytest.fixture
def source(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    src.mkdir()
    (src / "x").write_text("3")
    (src / "y").write_text("4")
    return src


def _run(scene: Path, source: Path | None, config: _Config | None = None, **kw) -> list[str]:
    CALLS.clear()
    PIPE.run(scene, config or _Config(), Reporter(quiet=True), source=source, **kw)
    return list(CALLS)


def test_second_run_is_cached(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    assert _run(scene, source) == ["a", "b"]
    assert (scene / "02_b" / "b.txt").read_text() == "14"
    assert _run(scene, source) == []
    manifest = json.loads((scene / "manifest.json").read_text())
    entry = manifest["stages"]["b"]
    assert entry["status"] == "done" and entry["wall_s"] >= 0 and "numpy" in entry["versions"]
    assert entry["files"]["b.txt"]["size"] == 2


def test_config_change_reruns_that_stage_and_downstream_only(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    assert _run(scene, source, _Config(b=_B(factor=3))) == ["b"]
    assert (scene / "02_b" / "b.txt").read_text() == "21"
    assert _run(scene, source, _Config(a=_A(value=2), b=_B(factor=3))) == ["a", "b"]


def test_source_change_reruns_everything(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    (source / "z").write_text("1")
    assert _run(scene, source) == ["a", "b"]
    (source / "z").unlink()
    assert _run(scene, source) == ["a", "b"]


def test_unchanged_upstream_output_keeps_downstream_cached(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    assert _run(scene, source, from_stage="a") == ["a"]  # forced, same output → b stays valid


def test_from_until_force(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    assert _run(scene, source, until_stage="a") == ["a"]
    assert not (scene / "02_b").exists()
    assert _run(scene, source, from_stage="b") == ["b"]
    assert _run(scene, source, force=True) == ["a", "b"]
    with pytest.raises(ReconError, match="Unknown stage"):
        _run(scene, source, from_stage="nope")


def test_downstream_alone_needs_upstream(tmp_path: Path, source: Path) -> None:
    with pytest.raises(ReconError, match="needs the output of 'a'"):
        _run(tmp_path / "scene", source, from_stage="b")


def test_failure_keeps_previous_complete_state(tmp_path: Path, source: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    monkeypatch.setenv("RECON_TEST_FAIL_B", "1")
    with pytest.raises(RuntimeError):
        _run(scene, source, _Config(b=_B(factor=5)))
    assert (scene / "02_b" / "b.txt").read_text() == "14"  # the old complete output is intact
    assert not [p for p in scene.iterdir() if p.name.startswith(".tmp-")]
    rows = {r["stage"]: r for r in PIPE.state(scene)}
    assert rows["b"]["state"] == "done" and "boom" in rows["b"]["error"]
    monkeypatch.delenv("RECON_TEST_FAIL_B")
    assert _run(scene, source, _Config(b=_B(factor=5))) == ["b"]


def test_corrupted_artifact_is_detected_and_rerun(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    (scene / "02_b" / "b.txt").write_text("99")
    assert {r["stage"]: r["state"] for r in PIPE.state(scene)}["b"] == "corrupt"
    assert _run(scene, source) == ["b"]
    assert (scene / "02_b" / "b.txt").read_text() == "14"


def test_corrupted_manifest_means_rerun_not_crash(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    (scene / "manifest.json").write_text('{"stages": {"a": ')
    assert _run(scene, source) == ["a", "b"]
    assert Manifest(scene).warning is None


def test_leftover_temporary_folders_are_cleaned(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)
    (scene / ".tmp-02_b-12345").mkdir()
    (scene / ".tmp-02_b-12345" / "b.txt").write_text("half")
    assert _run(scene, source) == []
    assert not (scene / ".tmp-02_b-12345").exists()


def test_output_path_that_is_a_file(tmp_path: Path, source: Path) -> None:
    target = tmp_path / "file"
    target.write_text("x")
    with pytest.raises(ReconError, match="is a file"):
        _run(target, source)


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores directory permissions")
def test_read_only_output_folder(tmp_path: Path, source: Path) -> None:
    scene = tmp_path / "ro"
    scene.mkdir()
    scene.chmod(0o555)
    with pytest.raises(ReconError, match="not writable"):
        _run(scene, source)


def _hold_lock(scene: str, ready: multiprocessing.synchronize.Event, release: multiprocessing.synchronize.Event) -> None:
    with scene_lock(Path(scene)):
        ready.set()
        release.wait(10)


def test_second_writer_is_refused_and_dead_holder_releases(tmp_path: Path) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    ctx = multiprocessing.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    proc = ctx.Process(target=_hold_lock, args=(str(scene), ready, release))
    proc.start()
    assert ready.wait(10)
    with pytest.raises(ReconError, match="in use by another recon process"):
        with scene_lock(scene):
            pass
    assert running_pid(scene) == str(proc.pid)
    Manifest(scene).save()
    shown = CliRunner().invoke(app, ["status", str(scene)], env={"COLUMNS": "300"})
    assert shown.exit_code == 0 and f"a recon run (pid {proc.pid}) is writing this scene now" in shown.output
    proc.kill()  # a dead process must not hold the lock forever
    proc.join()
    assert running_pid(scene) is None
    with scene_lock(scene):
        pass
    assert "is writing this scene" not in CliRunner().invoke(app, ["status", str(scene)]).output


def test_a_run_waits_out_the_instant_status_looks_at_the_lock(tmp_path: Path) -> None:
    """`recon status` takes the scene's lock shared for an instant; a run starting then must not be refused."""
    scene = tmp_path / "scene"
    scene.mkdir()
    with scene_lock(scene):
        pass
    fd = os.open(scene / ".lock", os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_SH)
    threading.Timer(0.3, os.close, (fd,)).start()  # closing the file releases the lock
    with scene_lock(scene):
        assert running_pid(scene) == str(os.getpid())  # held: seen through another open file, this process's too


def test_every_run_appends_what_it_showed_to_the_scene_log(tmp_path: Path, source: Path, monkeypatch) -> None:
    scene = tmp_path / "scene"
    _run(scene, source)  # quiet: the terminal shows nothing, the log keeps it all the same
    monkeypatch.setenv("RECON_TEST_FAIL_B", "1")
    with pytest.raises(RuntimeError, match="boom"):
        _run(scene, source, _Config(b=_B(factor=3)))
    lines = (scene / "logs" / "run.log").read_text().splitlines()
    text = "\n".join(lines)
    assert text.count("run: photos") == 2  # appended, the first run's lines kept
    assert "a done in" in text and "b done in" in text and "finished" in text
    assert "a: up to date (cached)" in text  # the second run reused a
    assert lines[-1].endswith("stopped: RuntimeError: boom")  # how the second run ended
    assert all(line[:4].isdigit() for line in lines)  # each line dated


def test_a_log_keeps_plain_text_of_marked_up_lines(tmp_path: Path) -> None:
    report = Reporter(quiet=True)
    report.log_to(tmp_path / "logs" / "run.log")
    report.info("[bold]preset[/] fast", markup=True)
    report.info("a path [with brackets]")
    report.warn("careful")
    report.log_to(None)
    report.info("after the log closed")
    text = (tmp_path / "logs" / "run.log").read_text()
    assert "preset fast" in text and "[bold]" not in text
    assert "a path [with brackets]" in text and "warning: careful" in text
    assert "after the log closed" not in text


def test_a_log_that_cannot_be_written_does_not_stop_the_run(tmp_path: Path) -> None:
    (tmp_path / "logs").write_text("a file where the log folder would be")
    report = Reporter(quiet=True)
    report.log_to(tmp_path / "logs" / "run.log")
    report.info("the run goes on")
    report.log_to(None)
    assert any("cannot be written" in w for w in report.warnings)


@dataclass
class _Trained:
    budget: int = 1
    other: int = 0


@dataclass
class _TrainedConfig(RunConfig):
    a: _A = field(default_factory=_A)
    c: _Trained = field(default_factory=_Trained)


SEEN: list[str | None] = []


def _stage_c(ctx: StageContext) -> dict:
    """Writes its budget; says which budget its `previous` output was made under (None: none handed over)."""
    SEEN.append((ctx.previous / "c.txt").read_text() if ctx.previous else None)
    (ctx.out / "c.txt").write_text(str(ctx.config.budget))
    return {}


def test_a_stage_gets_its_output_made_under_options_that_differ_only_in_what_its_scratch_survives(
        tmp_path: Path, source: Path) -> None:
    """What lets a longer budget train a finished field on: `previous` is the stage's output when only a
    `scratch_survives` field changed; not for other changes, nor for a forced run of the same options."""
    pipe = Pipeline([Stage("a", "01_a", (), 1, _stage_a, needs_source=True, source_digest=_digest_source),
                     Stage("c", "02_c", ("a",), 1, _stage_c, scratch_survives=("budget",))])
    scene = tmp_path / "scene"
    SEEN.clear()
    for config, force in [(_Trained(budget=1), False), (_Trained(budget=2), False), (_Trained(budget=2), False),
                          (_Trained(budget=3), False), (_Trained(budget=3), True), (_Trained(budget=4, other=1), False),
                          (_Trained(budget=5, other=1), False)]:
        pipe.run(scene, _TrainedConfig(c=config), Reporter(quiet=True), source=source, force=force)
    # the third run is cached; the forced one starts again; other=1 starts again, then hands on under it
    assert SEEN == [None, "1", "2", None, None, "4"]
    (scene / "02_c" / "c.txt").write_text("changed by hand")  # an output whose files changed is not trained on
    pipe.run(scene, _TrainedConfig(c=_Trained(budget=6, other=1)), Reporter(quiet=True), source=source)
    assert SEEN[-1] is None


@dataclass
class _Nested:
    box: tuple[float, ...] = (-1.0, 1.0)  # kept as a list in the manifest: unchanged all the same
    res: int = 64


@dataclass
class _C:
    budget: int = 1
    grid: _Nested = field(default_factory=_Nested)


@dataclass
class _ReasonConfig(RunConfig):
    a: _A = field(default_factory=_A)
    c: _C = field(default_factory=_C)


def test_a_finished_stage_run_again_says_why(tmp_path: Path, source: Path) -> None:
    """Running a finished stage again is a choice the run explains: the options that changed (nested sections key by
    key), the upstream output or the photos that changed, a new recipe; and whether its output is carried on.
    `recon status` with options says the same of its stale stages."""
    import io

    from rich.console import Console

    def run(config: _ReasonConfig, version: int = 1, preset: str | None = None,
            photos: Path = source) -> tuple[list[str], Pipeline]:
        said = io.StringIO()
        pipe = Pipeline([Stage("a", "01_a", (), 1, _stage_a, needs_source=True, source_digest=_digest_source),
                         Stage("c", "02_c", ("a",), version, _stage_c, scratch_survives=("budget",))])
        pipe.run(scene, config, Reporter(Console(file=said, width=400, color_system=None)), source=photos,
                 preset=preset)
        return [line for line in said.getvalue().splitlines() if "runs again" in line], pipe

    scene = tmp_path / "scene"
    assert run(_ReasonConfig())[0] == []  # the first run
    assert run(_ReasonConfig())[0] == []  # cached
    assert run(_ReasonConfig(c=_C(budget=2)))[0] == ["c runs again: c.budget 1 → 2"]  # carried on: the stage says how
    assert run(_ReasonConfig(c=_C(budget=2, grid=_Nested(res=96))))[0] == [
        "c runs again: c.grid.res 64 → 96; made anew (only a change of c.budget carries its output on)"]
    (source / "x").write_text("5")
    told, pipe = run(_ReasonConfig(c=_C(budget=2, grid=_Nested(res=96))))
    assert told[0] == "a runs again: the photos changed" and told[1].startswith("c runs again: the a stage's output")
    told, pipe = run(_ReasonConfig(c=_C(budget=2, grid=_Nested(res=96))), version=2)
    assert told == ["c runs again: this recon makes it differently (stage version 1 → 2); made anew (only a change "
                    "of c.budget carries its output on)"]
    rows = {r["stage"]: r for r in pipe.state(scene, _ReasonConfig(a=_A(value=3), c=_C(budget=2)), source)}
    assert rows["a"]["why"] == "a.value 1 → 3" and rows["c"]["why"] == "c.grid.res 96 → 64"
    rows = {r["stage"]: r for r in pipe.state(scene, _ReasonConfig(a=_A(value=3), c=_C(budget=2, grid=_Nested(res=96))),
                                               source)}
    assert rows["a"]["state"] == "stale" and rows["c"]["state"] == "done"  # whether c runs again, a's output tells
    assert rows["c"]["why"] == "if a's new output differs from its last"
    assert "why" not in pipe.state(scene)[1]  # without options nothing is stale here
    # an entry made under no named preset names none; one made under a preset names it and the one that replaces it
    assert run(_ReasonConfig(c=_C(budget=3, grid=_Nested(res=96))), 2, "fast")[0] == ["c runs again: c.budget 2 → 3"]
    told, pipe = run(_ReasonConfig(c=_C(budget=3, grid=_Nested(res=64))), 2, "quality")
    assert told == ["c runs again: preset fast → quality, c.grid.res 96 → 64; made anew (only a change of c.budget "
                    "carries its output on)"]
    rows = {r["stage"]: r for r in pipe.state(scene, _ReasonConfig(c=_C(budget=3, grid=_Nested(res=96))), source,
                                              preset="fast")}
    assert rows["c"]["why"] == "preset quality → fast, c.grid.res 64 → 96" and "why" not in rows["a"]
    moved = tmp_path / "moved"  # the same photos from another folder: nothing runs again
    os.rename(source, moved)
    assert run(_ReasonConfig(c=_C(budget=3, grid=_Nested(res=64))), 2, "quality", photos=moved)[0] == []
    assert Manifest(scene).data["source"] == str(moved)  # where later commands find them
    other = tmp_path / "other"  # moved and changed: both said
    os.rename(moved, other)
    (other / "x").write_text("6")
    told, _ = run(_ReasonConfig(c=_C(budget=3, grid=_Nested(res=64))), 2, "quality", photos=other)
    assert told[0] == f"a runs again: the photos changed (read from {other} now, not {moved})", told


def test_a_project_folder_moved_whole_finds_its_photos_from_the_scene(tmp_path: Path) -> None:
    """Photos and scene in one project folder, moved together: the recorded photos path is gone, the same path from
    the scene folder finds them, so a run without the photos (and every command reading them) goes on cached."""
    project = tmp_path / "project"
    photos = project / "photos"
    photos.mkdir(parents=True)
    (photos / "x").write_text("3")
    assert _run(project / "scene", photos) == ["a", "b"]
    moved = tmp_path / "elsewhere" / "project moved"
    moved.parent.mkdir()
    project.rename(moved)
    manifest = Manifest(moved / "scene")
    assert manifest.source == moved / "photos" and manifest.data["source"] == str(photos)
    assert [row["state"] for row in PIPE.state(moved / "scene")] == ["done", "done"]
    assert _run(moved / "scene", None) == []  # cached, from the photos where they are now
    assert Manifest(moved / "scene").data["source"] == str(moved / "photos")
    shutil.rmtree(moved / "photos")
    assert Manifest(moved / "scene").source == moved / "photos"  # gone both ways: the last path, for the error


def test_status_without_options_tells_changed_photos_and_hashes_only_what_looks_changed(tmp_path: Path) -> None:
    """`recon status` given no options said "done" for photos edited since poses ran (the fingerprint needs the
    options); the names, sizes and times kept in the manifest tell it now, and the photos are hashed only where those
    differ: a photo touched with the same bytes is hashed once, then its new time is kept by the next (cached) run."""
    from recon.stages import POSES

    hashed: list[str] = []

    def digest(source: Path, cfg: object) -> str:
        hashed.append(source.name)
        return POSES.source_digest(source, cfg)  # type: ignore[misc]

    edit_while_running: list[Path] = []

    def poses(ctx: StageContext) -> dict:
        (ctx.out / "n.txt").write_text(str(len(list(ctx.source.iterdir()))))
        for path in edit_while_running:
            path.write_bytes(b"edited while the stage ran")
        return {}

    def later(ctx: StageContext) -> dict:
        (ctx.out / "m.txt").write_text((ctx.inputs["poses"] / "n.txt").read_text())
        return {}

    pipe = Pipeline([Stage("poses", "01_poses", (), 1, poses, needs_source=True, source_digest=digest,
                           source_stat=POSES.source_stat), Stage("later", "02_later", ("poses",), 1, later)])
    photos, scene = tmp_path / "photos", tmp_path / "scene"
    photos.mkdir()
    for name in ("a.jpg", "b.jpg"):
        (photos / name).write_bytes(name.encode() * 100)
    config = _Config()
    pipe.run(scene, config, Reporter(quiet=True), source=photos)

    def row() -> dict:
        hashed.clear()
        return pipe.state(scene)[0]

    assert row()["state"] == "done" and hashed == []  # the same names, sizes and times: nothing read
    assert [r["state"] for r in pipe.state(scene)] == ["done", "done"]
    os.utime(photos / "a.jpg", ns=(1, 1))  # touched, the same bytes
    assert row()["state"] == "done" and hashed == ["photos"]
    pipe.run(scene, config, Reporter(quiet=True), source=photos)  # cached: keeps the new time
    assert row()["state"] == "done" and hashed == []
    (photos / "b.jpg").write_bytes(b"edited")
    assert (row()["state"], row().get("why")) == ("stale", "the photos changed")
    for options in (None, config):  # the stages after it run again too: their input stands for other photos
        assert [(r["state"], r.get("why")) for r in pipe.state(scene, options)][1] == (
            "stale", "after poses, made from other photos")
    (photos / "b.jpg").write_bytes(b"b.jpg" * 100)
    (photos / "c.jpg").write_bytes(b"one more")  # a photo added
    assert row()["state"] == "stale"
    (photos / "c.jpg").unlink()
    edit_while_running.append(photos / "a.jpg")  # the stage ran on the bytes before: stale, though made after it
    pipe.run(scene, config, Reporter(quiet=True), source=photos, force=True)
    assert row()["state"] == "stale"
    os.rename(photos, tmp_path / "moved")  # gone: `recon run` says so, status shows what was made
    assert row()["state"] == "done"


def test_status_says_the_photos_are_gone(tmp_path: Path, source: Path) -> None:
    """Training or meshing again reads the photos where the poses found them: `recon status` says when they are not
    there any more (it raised, given options, and said nothing without)."""
    scene = tmp_path / "scene"
    manifest = Manifest(scene.mkdir() or scene)
    manifest.data["source"] = str(source)
    manifest.stages["poses"] = {"status": "done", "files": {}, "source_digest": "made from other photos"}
    (scene / "01_poses").mkdir()
    manifest.save()
    for options in ([], ["--preset", "fast"]):
        shown = CliRunner().invoke(app, ["status", str(scene), *options], env={"COLUMNS": "300"})
        assert shown.exit_code == 0 and "are not there" not in shown.output, shown.output
    os.rename(source, tmp_path / "moved")
    for options in ([], ["--preset", "fast"]):
        shown = CliRunner().invoke(app, ["status", str(scene), *options], env={"COLUMNS": "300"})
        assert shown.exit_code == 0 and f"the photos {source} are not there (moved or deleted)" in shown.output
        assert "│ poses     │ done" in shown.output


def test_an_option_added_or_removed_since_the_stage_ran_is_named_as_such() -> None:
    from recon.runner.pipeline import _changed_options

    assert _changed_options("train", {"lr": 0.01, "gone": 1}, {"lr": 0.01, "small_object": "auto"}) == [
        "train.gone (no longer an option)", "train.small_object auto (an option new in this recon)"]
    assert _changed_options("train", {"lr": 0.01, "span": None}, {"lr": 0.01, "span": 4}) == ["train.span null → 4"]
