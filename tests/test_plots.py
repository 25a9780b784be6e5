"""The training curves a user reads in 03_field/curves.png."""
from __future__ import annotations

from pathlib import Path

import pytest


def test_the_curves_mark_where_training_went_on_under_another_budget(tmp_path: Path, monkeypatch) -> None:
    import recon.plots as plots

    drawn = []
    save = plots._save
    monkeypatch.setattr(plots, "_save", lambda fig, path: (drawn.append(fig), save(fig, path)))
    history = [{"step": s, "loss": 0.01 / s, "psnr": 20 + s / 100, "time_s": s / 2} for s in range(10, 210, 10)]
    evals = [{"step": 100, "time_s": 50.0, "psnr": 22.0}]
    resumes = [{"step": 120, "time_s": 60.0, "from": "finished field", "budget_before": "4m", "budget": "8m"},
               {"step": 160, "time_s": 80.0, "from": "checkpoint", "budget_before": "8m", "budget": "8m"}]
    plots.training_curves(history, evals, tmp_path / "curves.png", resumes=resumes)
    assert (tmp_path / "curves.png").stat().st_size > 0
    axes = drawn[0].axes
    for ax, xs in zip(axes, ([120, 160], [60.0, 80.0], [120, 160]), strict=True):
        dashed = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert [line.get_xdata()[0] for line in dashed] == pytest.approx(xs)
    named = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert "went on from the finished field (4m → 8m)" in named and "went on from the checkpoint" in named
