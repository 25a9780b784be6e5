"""Helpers for the fault tests: a tiny synthetic capture, `recon run` in a real subprocess, artifact comparison."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGE_FOLDERS = {"poses": "01_poses", "normalize": "02_scene", "train": "03_field", "mesh": "04_mesh"}
TINY = [
    "train.steps=40", "train.max_side=32", "train.batch_rays=256", "train.eval_every=20", "train.checkpoint_every=10",
    "train.final_eval_views=1", "train.eval_views=1", "mesh.resolution=24", "mesh.color=field", "mesh.texture_size=64",
]
"""Tiny settings: the whole pipeline in ~20 s on one CPU core."""


def make_capture(folder: Path, views: int = 8, size: int = 64) -> Path:
    """A synthetic transforms.json capture (imported: no SfM), deterministic bytes."""
    sys.path.insert(0, str(REPO / "fixtures"))
    try:
        from generate import generate
    finally:
        sys.path.pop(0)
    generate(folder, scene="blocks", views=views, size=size, mesh_res=32, mesh_faces=None)
    return folder


def cli_args(source: Path, scene: Path, *extra: str, settings: list[str] | None = None) -> list[str]:
    args = [sys.executable, "-m", "recon.app.cli", "run", str(source), "--out", str(scene)]
    for item in TINY if settings is None else settings:
        args += ["--set", item]
    return args + list(extra)


def env(fault: str | None = None) -> dict[str, str]:
    # the repo first, then whatever the caller's PYTHONPATH holds (packages installed with pip --target, say)
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    e = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "COLUMNS": "400", "PYTHONPATH": path}
    e.pop("RECON_FAULT", None)
    if fault:
        e["RECON_FAULT"] = fault
    return e


def run(source: Path, scene: Path, *extra: str, fault: str | None = None, settings: list[str] | None = None,
        timeout: float = 180) -> subprocess.CompletedProcess:
    """`recon run` in a fresh process (optionally with a RECON_FAULT injected)."""
    return subprocess.run(cli_args(source, scene, *extra, settings=settings), env=env(fault), cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def recon_noting_torch(*args: str) -> subprocess.CompletedProcess:
    """`recon ARGS` in a fresh process, its last line saying the exit code and whether torch was loaded."""
    probe = ("import sys\nfrom recon.app.cli import app\ntry:\n    app(sys.argv[1:], prog_name='recon')\n"
             "except SystemExit as exc:\n    print('exit', exc.code or 0, 'torch loaded', 'torch' in sys.modules)")
    return subprocess.run([sys.executable, "-c", probe, *args], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env=env())


def _ctrl_c_stops() -> None:
    """In the child: SIGINT as a terminal delivers it. A test suite started in the background (`cmd &`, as CI or nohup
    may) has SIGINT ignored, and a child inherits that, so a Ctrl-C test's signal would be lost."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(source: Path, scene: Path, *extra: str, settings: list[str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(cli_args(source, scene, *extra, settings=settings), env=env(), cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_ctrl_c_stops)


def wait_for(predicate, timeout: float = 120, what: str = "condition") -> None:
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def checkpoint_of(scene: Path) -> Path | None:
    found = sorted((scene / ".work").glob("train-*/checkpoint.pt")) if (scene / ".work").is_dir() else []
    return found[0] if found else None


def manifest(scene: Path) -> dict:
    path = scene / "manifest.json"
    return json.loads(path.read_text()) if path.is_file() else {"stages": {}}


def finished_times(scene: Path) -> dict[str, str]:
    """Stage → its manifest 'finished' time, for stages recorded as done."""
    return {k: v["finished"] for k, v in manifest(scene)["stages"].items() if v.get("status") == "done"}


def same_bytes(a: Path, b: Path) -> bool:
    return a.read_bytes() == b.read_bytes()


def assert_same_result(scene: Path, reference: Path) -> None:
    """Deterministic stages (poses import, normalize) bitwise equal to the uninterrupted run's; training and what
    follows it within noise (multi-threaded float sums are not bit-reproducible across processes): the same
    held-out PSNR within 0.5 dB and a mesh of about the same size."""
    for rel in ("01_poses/scene.json", "01_poses/points.npz", "02_scene/scene.json", "02_scene/points.npz"):
        assert same_bytes(scene / rel, reference / rel), f"{rel} differs from the uninterrupted run's"
    ours, ref = manifest(scene)["stages"], manifest(reference)["stages"]
    assert abs(ours["train"]["summary"]["psnr"] - ref["train"]["summary"]["psnr"]) < 0.5
    if "mesh" in ref:
        a = json.loads((scene / "04_mesh" / "mesh_report.json").read_text())
        b = json.loads((reference / "04_mesh" / "mesh_report.json").read_text())
        assert abs(a["faces"] - b["faces"]) <= 0.1 * b["faces"] + 10, (a["faces"], b["faces"])


def kill_tree(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
    proc.wait(30)
