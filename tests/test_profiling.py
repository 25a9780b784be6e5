"""recon bench --profile's bookkeeping: labels wrapped around functions get the time of their calls (and of
nothing else), row counts are recorded per function, and the wrapped functions are restored."""
from __future__ import annotations

import types

import pytest
import torch

from recon.app.profiling import BACKWARD_KINDS, _labelled, attribute
from recon.nerf.native import native_marcher


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


@pytest.mark.skipif(native_marcher() is None, reason="the native library did not build here (no cc)")
def test_a_grids_backward_in_c_is_a_part_of_its_own() -> None:
    """The grids' C backward (recon.nerf.grid._NativeRead's node) is named by BACKWARD_KINDS, not left in the
    catch-all 'compositing bwd'."""
    from recon.nerf.grid import DenseGrid

    grid = DenseGrid(48, 8, init_std=0.1)
    x = torch.rand(50_000, 3)
    prof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    with prof:
        grid(x).sum().backward()
    parts = attribute(prof)
    native_part = dict(BACKWARD_KINDS)["NativeRead"]
    assert parts.get(native_part, 0) > 0
    assert parts[native_part] > parts.get("compositing bwd", 0)
