"""recon bench --profile's bookkeeping: labels wrapped around functions get the time of their calls (and of
nothing else), row counts are recorded per function, and the wrapped functions are restored."""
from __future__ import annotations

import types

import pytest
import torch

from recon.app.profiling import BACKWARD_KINDS, _labelled, _part, attribute
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
    native_part = dict(BACKWARD_KINDS)["NativeRead"]
    backward = {ev.name: _part(ev) for ev in prof.events()
                if ev.cpu_parent is None and ev.name.startswith("autograd::engine::evaluate_function")}
    natives = [name for name in backward if "NativeRead" in name]
    assert natives and all(backward[name] == native_part for name in natives), backward
    assert attribute(prof).get(native_part, 0) > 0  # its time is counted where it is named


@pytest.mark.skipif(native_marcher() is None, reason="the native library did not build here (no cc)")
def test_the_marched_densities_backward_is_the_grids_part() -> None:
    """The density levels' C backward behind the march's densities (recon.nerf.fast._MarchedDensity's node) is
    counted with the grids' native backward, not in 'compositing bwd'."""
    from recon.nerf.fast import FastConfig, FastModel

    model = FastModel(FastConfig(density_res=32, feature_res=16))
    u = torch.rand(50_000, 3)
    with torch.no_grad():
        sigma = model._sigma_unit(u)
    prof = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
    with prof:
        model._marched_sigma(sigma, u).sum().backward()
    backward = {ev.name: _part(ev) for ev in prof.events()
                if ev.cpu_parent is None and ev.name.startswith("autograd::engine::evaluate_function")}
    marched = [name for name in backward if "MarchedDensity" in name]
    assert marched and all(backward[name] == dict(BACKWARD_KINDS)["MarchedDensity"] for name in marched), backward
    assert dict(BACKWARD_KINDS)["MarchedDensity"] == dict(BACKWARD_KINDS)["NativeRead"]


def test_profile_md_says_where_and_under_what_load_it_ran() -> None:
    """A profile's milliseconds mean nothing without the commit, the CPU and the load they were taken under."""
    from recon.app.profiling import markdown

    limits = {"threads": 2.0, "matmul_fp32_gflops": 1234.5, "matmul_bf16_gflops": 0.326,
              "matmul_mlp_shape_gflops": 300.0, "copy_gbs": 20.0, "gather_gbs": 3.0}
    result = {"preset": "fast", "data": "lego-half", "warmup": 150, "profiled_steps": 4, "device": "cpu", "batch_rays": 4096,
              "samples_per_ray": 16.0, "colored_per_ray": 10.0, "params": 3e7, "wall_s": 0.4, "pieces": [],
              "parts": {"marcher": 0.1, "Adam step": 0.2}, "top_ops": "ops"}
    where = {"date": "2026-12-04T16:00:00+00:00", "commit": "0123456789abcdef", "uncommitted_changes": True,
             "machine": {"cpu": "Example CPU"}, "load_average_start": [0.5, 0.7, 0.9],
             "load_average_end": [1.6, 1.2, 1.1]}
    text = markdown([result], limits, where)
    head = text.splitlines()[2]
    assert "Commit 0123456 with uncommitted changes" in head and "Example CPU" in head
    assert "0.50 / 0.70 / 0.90 at the start" in head and "1.60 / 1.20 / 1.10 at the end" in head
    assert "40,960 rays/s while profiled" in text
    assert "| matmul 2048² fp32 | 1,234 GFLOP/s |" in text and "| matmul 2048² bf16 | 0.33 GFLOP/s |" in text
