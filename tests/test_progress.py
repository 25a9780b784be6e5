"""What a user watches: the progress bar's count, elapsed time and ETA fit an 80-column terminal, and a training
run with a time budget counts toward the steps the budget allows, not toward a step cap it never reaches."""
from __future__ import annotations

import io
import re
import time

import pytest
import torch
from rich.console import Console

from recon.app.progress import Reporter
from recon.stages.train import ESTIMATE_AFTER_S, FEW_STEPS, expected_steps, few_steps_warning, resumed_budget_note


@pytest.mark.parametrize(("stage", "description", "unit", "info"), [
    ("train", "training", "steps", "loss 0.0006  PSNR 32.23 dB  31,694 rays/s"),
    ("mesh", "rendering the meshes into the held-out views", "views", ""),
])
def test_a_bar_keeps_its_count_and_times_in_80_columns(stage: str, description: str, unit: str, info: str) -> None:
    buf = io.StringIO()
    reporter = Reporter(console=Console(file=buf, width=80, force_terminal=True, color_system=None))
    reporter.current_stage = stage
    with reporter.task(description, total=12000, unit=unit) as bar:
        bar.update(completed=530, total=2140, info=info)
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", buf.getvalue().split("\r")[-1])
    assert f"530/2140 {unit}" in text and re.search(r"\d:\d\d:\d\d ETA", text)
    assert all(word in text.split() for word in info.split())  # the status text wraps, none of it is cut
    assert all(len(line.rstrip()) <= 80 for line in text.splitlines())


def test_expected_steps_follows_the_budget_when_it_comes_before_the_cap() -> None:
    # 500 steps in 60 s of a 240-s budget: 2,000 steps in all, far under the 12,000-step cap
    assert expected_steps(500, 60.0, 0, 0.0, 240.0, 12000) == 2000
    # a fast machine reaches the cap first: the cap
    assert expected_steps(5000, 60.0, 0, 0.0, 240.0, 12000) == 12000
    # no budget, or too little of this run to measure a rate: the cap
    assert expected_steps(500, 60.0, 0, 0.0, 0.0, 12000) == 12000
    assert expected_steps(20, ESTIMATE_AFTER_S / 2, 0, 0.0, 240.0, 12000) == 12000
    # the rate since the given step and time (the last 30 s, or since a resumed run started): 470 steps in 60 s
    assert expected_steps(1000, 121.0, 530, 61.0, 240.0, 12000) == 1930  # 1,000 + 470/60 × 119 s left
    # the budget spent: never under the steps already done
    assert expected_steps(2013, 250.0, 0, 0.0, 240.0, 12000) == 2013


def test_a_budget_too_short_for_this_machine_is_said_with_the_budget_that_is_not() -> None:
    # half of a 240-s budget spent at step 80, now 1.1 steps/s: about 212 steps in all; 1,000 steps at that rate
    # need 120 s + 920 / 1.1 s = 956 s, 16 minutes
    said = few_steps_warning(212, 80, 120.0, 1.1, "4m", 12000)
    assert said is not None and "trains about 212 steps" in said
    assert f"`--budget 16m` trains {FEW_STEPS:,} or more" in said
    # enough steps, a step cap that stops training first, or no rate yet: nothing to say
    assert few_steps_warning(FEW_STEPS, 500, 120.0, 4.2, "4m", 12000) is None
    assert few_steps_warning(212, 80, 120.0, 1.1, "4m", 200) is None
    assert few_steps_warning(212, 80, 120.0, 0.0, "4m", 12000) is None


def test_the_train_stage_warns_while_a_budget_can_still_be_changed(tmp_path, monkeypatch) -> None:
    """Once half the budget is spent the stage judges the steps it allows, once, as a warning; `recon run`
    says its warnings again under the table that ends it (they came above a screenful of reasons)."""
    import recon.app.cli as cli
    import recon.stages.train as train_stage
    from tests import faults

    monkeypatch.setattr(train_stage, "FEW_STEPS", 10**9)  # every machine is too slow for this many
    shown, said = io.StringIO(), io.StringIO()
    monkeypatch.setattr(cli, "out_console", Console(file=shown, width=400, color_system=None))
    monkeypatch.setattr(cli, "console", Console(file=said, width=400, color_system=None))
    capture = faults.make_capture(tmp_path / "capture")
    settings = [*faults.TINY, "train.steps=100000000", "train.budget=8s", "train.eval_every=0", "train.checkpoint_every=0"]
    cli._run(tmp_path / "scene", capture, "fast", settings, quiet=False, until_stage="train")
    warned = [line for line in said.getvalue().splitlines() if "budget trains about" in line]
    assert len(warned) == 1 and "the 8s budget" in warned[0] and "`--budget " in warned[0]
    end = shown.getvalue().split("recon — ")[-1]
    assert "1 warning in this run" in end and "- at this machine's pace" in end and "budget trains about" in end


def test_another_budget_trains_on_from_the_checkpoint_of_a_stopped_run(tmp_path, monkeypatch) -> None:
    """What the short-budget warning advises: Ctrl-C, then the same command with another --budget goes on from the
    last checkpoint (the stage's scratch outlives a change of budget), its curve and time carried over."""
    import json

    import typer

    import recon.app.cli as cli
    import recon.stages.train as train_stage
    from recon.runner.pipeline import SCRATCH_NOTE
    from tests import faults

    write = train_stage.write_json_atomic

    def write_then_stop(path, data):
        write(path, data)
        if path.name == SCRATCH_NOTE:
            raise KeyboardInterrupt  # Ctrl-C right after the first checkpoint and its note

    said = io.StringIO()
    monkeypatch.setattr(cli, "console", Console(file=said, width=400, color_system=None))
    monkeypatch.setattr(cli, "out_console", Console(file=io.StringIO(), width=400, color_system=None))
    monkeypatch.setattr(train_stage, "write_json_atomic", write_then_stop)
    capture = faults.make_capture(tmp_path / "capture")
    settings = [*faults.TINY, "train.steps=100000000", "train.eval_every=0", "train.checkpoint_every=15"]
    with pytest.raises((KeyboardInterrupt, typer.Exit)):
        cli._run(tmp_path / "scene", capture, "fast", [*settings, "train.budget=10m"], quiet=False, until_stage="train")
    stopped = torch.load(faults.checkpoint_of(tmp_path / "scene"), weights_only=False)
    assert stopped["state"]["step"] == 15 and stopped["budget"] == "10m"
    rows = {row["stage"]: row for row in cli._pipeline().state(tmp_path / "scene")}
    assert rows["train"]["state"] == "missing" and "training checkpoint at step 15" in rows["train"]["scratch"]
    assert "under a 10m budget" in rows["train"]["scratch"] and "MB in .work/train-" in rows["train"]["scratch"]
    assert "scratch" not in rows["normalize"]
    monkeypatch.setattr(train_stage, "write_json_atomic", write)
    budget = f"train.budget={int(stopped['train_time_s']) + 3}s"  # 2-3 s more than the checkpoint's training time
    cli._run(tmp_path / "scene", capture, "fast", [*settings, budget], quiet=False, until_stage="train")
    told = " ".join(said.getvalue().split())
    assert "resuming from the checkpoint at step 15" in told and "under a 10m budget" in told
    metrics = json.loads((tmp_path / "scene" / "03_field" / "metrics.json").read_text())
    assert metrics["steps"] > 15 and metrics["history"][0]["step"] == 10  # the first run's curve goes on
    assert metrics["train_time_s"] >= stopped["train_time_s"]
    assert [(r["step"], r["from"], r["budget_before"]) for r in metrics["resumes"]] == [(15, "checkpoint", "10m")]
    assert not list((tmp_path / "scene" / ".work").glob("train-*"))  # scratch removed once the stage is done
    assert not any("scratch" in row for row in cli._pipeline().state(tmp_path / "scene"))


def test_a_longer_budget_trains_a_finished_field_on_and_other_options_start_again(tmp_path, monkeypatch) -> None:
    """A run to the end, then the same command with a longer --budget: the finished field trains on from its step
    (its trained state beside it), the curve carried over, and so does `balanced` (fast's field, a longer budget); a
    shorter budget keeps it, and so does a change of the test views it is scored on; another option starts again."""
    import json

    import recon.app.cli as cli
    from recon.stages.train import TRAINED_STATE
    from tests import faults

    said = io.StringIO()
    monkeypatch.setattr(cli, "console", Console(file=said, width=400, color_system=None))
    monkeypatch.setattr(cli, "out_console", Console(file=io.StringIO(), width=400, color_system=None))
    capture, scene = faults.make_capture(tmp_path / "capture"), tmp_path / "scene"
    settings = [*faults.TINY, "train.steps=100000000", "train.eval_every=0"]

    def run(*extra: str, preset: str = "fast") -> tuple[str, dict]:
        said.seek(0)
        said.truncate()
        cli._run(scene, capture, preset, [*settings, *extra], quiet=False, until_stage="train")
        return " ".join(said.getvalue().split()), json.loads((scene / "03_field" / "metrics.json").read_text())

    told, first = run("train.budget=2s")
    assert "training on" not in told and (scene / "03_field" / TRAINED_STATE).is_file()
    told, longer = run("train.budget=4s")
    assert f"training on from the finished field at step {first['steps']:,}" in told and "under a 2s budget" in told
    assert longer["steps"] > first["steps"] and longer["history"][:len(first["history"])] == first["history"]
    assert longer["train_time_s"] >= 4.0
    assert [(r["step"], r["from"], r["budget_before"], r["budget"]) for r in longer["resumes"]] == [
        (first["steps"], "finished field", "2s", "4s")]
    told, balanced = run("train.budget=6s", preset="balanced")
    assert f"training on from the finished field at step {longer['steps']:,}" in told and "under a 4s budget" in told
    assert balanced["steps"] > longer["steps"] and [r["budget"] for r in balanced["resumes"]] == ["4s", "6s"]
    assert "train runs again: preset fast → balanced, train.budget 4s → 6s, train.depth_rays 256 → 512" in told
    shown = io.StringIO()  # `recon status --set`: the options on the preset the scene was run with, as a run takes them
    monkeypatch.setattr(cli, "out_console", Console(file=shown, width=400, color_system=None))
    cli.status(scene, None, [*settings, "train.budget=6s", "train.lr=0.02"])
    assert "runs again: train.lr" in shown.getvalue() and "depth_rays" not in shown.getvalue()
    told, shorter = run("train.budget=1s")
    assert "the 1s budget is spent already" in told and shorter["steps"] == balanced["steps"]
    assert "train runs again: preset balanced → fast" in told
    told, rescored = run("train.budget=1s", "train.final_eval_views=2")
    assert "the 1s budget is spent already" in told and rescored["steps"] == balanced["steps"]
    assert rescored["history"] == balanced["history"] and rescored["test"]["psnr"] == shorter["test"]["psnr"]
    told, other = run("train.budget=4s", "train.lr=0.003")
    assert "training on" not in told and "resuming" not in told
    assert other["history"][0] != first["history"][0]  # its own curve from step 0, not the first run's


def test_a_field_trained_to_the_step_cap_is_kept_under_a_longer_budget(tmp_path, monkeypatch) -> None:
    import json

    import recon.app.cli as cli
    from tests import faults

    said = io.StringIO()
    monkeypatch.setattr(cli, "console", Console(file=said, width=400, color_system=None))
    monkeypatch.setattr(cli, "out_console", Console(file=io.StringIO(), width=400, color_system=None))
    capture, scene = faults.make_capture(tmp_path / "capture"), tmp_path / "scene"
    settings = [*faults.TINY, "train.steps=12", "train.eval_every=0"]
    cli._run(scene, capture, "fast", [*settings, "train.budget=10m"], quiet=False, until_stage="train")
    cli._run(scene, capture, "fast", [*settings, "train.budget=20m"], quiet=False, until_stage="train")
    told = " ".join(said.getvalue().split())
    assert "training on from the finished field at step 12 of 12 (the step cap, reached: the field is kept" in told
    assert json.loads((scene / "03_field" / "metrics.json").read_text())["steps"] == 12


def test_a_finished_field_of_other_shapes_is_not_trained_on(tmp_path) -> None:
    from types import SimpleNamespace

    from recon.field import FIELD_FILE, save_field
    from recon.stages.train import TRAINED_STATE, _load_trained_state, _save_trained_state

    save_field(tmp_path / FIELD_FILE, "fast", {}, torch.nn.Linear(2, 3), {})
    _save_trained_state(tmp_path / TRAINED_STATE, {"state": {"step": 5}, "evals": [], "history": [],
                                                   "train_time_s": 1.0, "budget": "4m", "resumes": []})
    warned: list[str] = []
    report = SimpleNamespace(warn=warned.append)
    assert _load_trained_state(tmp_path, torch.nn.Linear(2, 3), report)["state"]["step"] == 5 and not warned
    assert _load_trained_state(tmp_path, torch.nn.Linear(2, 4), report) is None
    assert "cannot be trained on (its weights are not of the shapes this run builds); training starts over" in warned[0]


def test_what_a_checkpoint_made_under_another_budget_does_is_said() -> None:
    assert resumed_budget_note("4m", "4m", 120.0, 240.0) == ""
    assert "the 4m budget is spent already" in resumed_budget_note("4m", "4m", 241.0, 240.0)
    longer = resumed_budget_note("4m", "16m", 120.0, 960.0)
    assert "trained 120 s under a 4m budget" in longer and "about 840 s more" in longer
    assert "spent already" in resumed_budget_note("4m", "1m", 120.0, 60.0)
    assert "without a budget" in resumed_budget_note("4m", "", 120.0, 0.0)
    assert "under no budget" in resumed_budget_note("", "4m", 10.0, 240.0)


def test_a_batch_capture_keeps_its_warnings_for_batch_md(tmp_path, monkeypatch) -> None:
    """`recon batch` runs a capture without a screen: its warnings go into its record and batch.md's row."""
    import recon.stages.train as train_stage
    from recon.app.batch import _report_row, run_capture
    from tests import faults

    monkeypatch.setattr(train_stage, "FEW_STEPS", 10**9)
    capture = faults.make_capture(tmp_path / "capture")
    settings = [*faults.TINY, "train.steps=100000000", "train.budget=8s", "train.eval_every=0", "train.checkpoint_every=0"]
    record = run_capture(capture, tmp_path / "out" / "capture", "fast", settings)
    assert "error" not in record and len(record["warnings"]) == 1 and "budget trains about" in record["warnings"][0]
    row = _report_row(record)
    assert row.endswith(" |") and "warning: at this machine's pace" in row and row.count("|") == 8


def test_status_shows_when_a_stage_finished_in_the_readers_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """The manifest keeps UTC; `recon status` showed the raw stamp, seconds and offset included."""
    from recon.app.progress import local_minute

    monkeypatch.setenv("TZ", "Europe/Paris")
    time.tzset()
    try:
        assert local_minute("2026-12-06T23:33:24+00:00") == "2026-12-07 00:33"
    finally:
        monkeypatch.undo()
        time.tzset()
    assert local_minute(None) == "" and local_minute("last week") == "last week"
