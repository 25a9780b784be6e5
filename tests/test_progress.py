"""What a user watches: the progress bar's count, elapsed time and ETA fit an 80-column terminal, and a training
run with a time budget counts toward the steps the budget allows, not toward a step cap it never reaches."""
from __future__ import annotations

import io
import re

import pytest
from rich.console import Console

from recon.app.progress import Reporter
from recon.stages.train import ESTIMATE_AFTER_S, FEW_STEPS, expected_steps, few_steps_warning


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
