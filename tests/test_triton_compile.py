"""benchmarks/triton_compile.py: the hash grid's and the rays' Triton kernels, launched as a card's training launches
them, compile for an H100 (sm_90) on a machine without a GPU (Triton's LLVM and ptxas compile ahead of time for a
named target; the interpreter runs code a compiler refuses)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _nvidia_compiler() -> str | None:
    """Why Triton cannot compile for NVIDIA cards here, or None when it can."""
    try:
        from triton import knobs
        from triton.backends import backends
    except Exception as exc:  # not installed (e.g. macOS), or a build that does not load
        return f"triton does not import ({type(exc).__name__})"
    if "nvidia" not in backends:
        return "this triton has no NVIDIA backend"
    try:
        if not Path(knobs.nvidia.ptxas.path).is_file() or not Path(knobs.nvidia.cuobjdump.path).is_file():
            return "triton's ptxas or cuobjdump is missing"
    except Exception as exc:
        return f"triton's NVIDIA tools are not found ({type(exc).__name__})"
    return None


@pytest.mark.skipif(os.environ.get("TRITON_INTERPRET") == "1", reason="the tool runs its own interpreter process")
def test_the_hash_and_ray_kernels_compile_for_an_h100_as_a_card_launches_them(tmp_path: Path) -> None:
    why = _nvidia_compiler()
    if why:
        pytest.skip(why)
    out = tmp_path / "compile.json"
    run = subprocess.run([sys.executable, str(REPO / "benchmarks" / "triton_compile.py"), "--out", str(out),
                          "--targets", "90", "--kernels", "hash_fwd,hash_bwd,ray_box_fwd,pixel_rays_fwd", "--small",
                          "--models", "1", "--rays", "4"],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    (row,) = json.loads(out.read_text())
    launches = row["launches"]
    assert row["failed"] == 0 and launches and all(r["ok"] and r["target"] == "sm_90" for r in launches)
    # the card's hash grid (16 levels of 2 features) forward and backward; the train stage's probe launches the same
    hashes = [r for r in launches if r["kernel"].startswith("hash")]
    levels = {(r["kernel"], r["arguments"]["LEVELS"], r["arguments"]["F"]) for r in hashes}
    assert levels == {("hash_fwd", 16, 2), ("hash_bwd", 16, 2)}
    assert all(r["registers"] > 0 and r["num_warps"] >= 1 for r in launches)
    assert all(r["arguments"]["x"] == "*fp32" and r["arguments"]["res"] == "*i64" for r in hashes)
    # the fast model's clip to the box; a batch's rays with a scene box and with the photos' near and far
    rays = {(r["kernel"], r["arguments"].get("CLIP", r["arguments"].get("HAS_BOX"))) for r in launches
            if not r["kernel"].startswith("hash")}
    assert rays == {("ray_box_fwd", True), ("pixel_rays_fwd", True), ("pixel_rays_fwd", False)}
