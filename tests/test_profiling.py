"""recon bench --profile's bookkeeping: labels wrapped around functions get the time of their calls (and of
nothing else), row counts are recorded per function, and the wrapped functions are restored."""
from __future__ import annotations

import types

import torch

from recon.app.profiling import _labelled, attribute


def test_labels_attribute_time_and_count_rows_then_restore() -> None:
    mod = types.SimpleNamespace()
    mod.__dict__["heavy"] = lambda x: (x @ x.T).sum()
    original = mod.__dict__["heavy"]
    x = torch.randn(300, 64)
    prof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    with _labelled([(mod, "heavy", "recon:heavy part")]) as counts:
        with prof:
            mod.heavy(x)
            mod.heavy(x[:100])
            torch.ones(10).cumsum(0)  # outside any label
    assert mod.heavy is original
    assert counts["heavy"] == [300, 100]
    parts = attribute(prof)
    assert parts["recon:heavy part"[len("recon:"):]] > 0
    assert "other ops (loss, glue)" in parts  # the unlabelled op is counted apart
    assert set(parts) == {"heavy part", "other ops (loss, glue)"}
