"""benchmarks/gpu_check.py --smoke on a CPU: the GPU check that a device session runs works end to end here first
(poses imported, 80 training steps, the test views, a render timing, the mesh stage, its record), so minutes of a
card are not spent finding that it does not."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_gpu_check_runs_on_a_cpu_and_records_its_table(shared_data: Path, tmp_path: Path) -> None:
    lego = shared_data / "nerf_synthetic_lego_half"
    out = tmp_path / "check"
    done = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--data", str(lego), "--out",
                           str(out), "--smoke"], capture_output=True, text=True, timeout=600, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    row = json.loads((out / "gpu_check.json").read_text())[-1]
    run = row["runs"]["default"]
    assert run["steps"] == 80 and run["test_views"] == 2
    assert math.isfinite(run["psnr"]) and run["psnr"] > 10.0  # 80 steps learn the white backdrop at least
    assert run["mesh_stage_s"] is not None and run["render_ms_per_view"] > 0
    phases = run["train_phases_s"]  # where the train stage's time goes besides its budget
    assert {"plan", "build", "train", "final_evaluation", "save"} <= set(phases) and "warm_up" not in phases  # a CPU
    assert sum(phases.values()) <= run["stage_wall_s"]["train"] + 0.1
    assert "train stage's parts" in (out / "gpu_check.md").read_text()
    assert row["host"]["cpu_count"] >= 1 and row["host"]["project_1m_blas_ms"] > 0  # the host's CPU side, probed
    assert (out / "gpu_check.md").read_text().count("|") > 10
