"""Same results before and after a refactor: the shipped sample, a fixed seed and step count, one thread.

Runs `recon run fixtures/sample/images --preset fast` with `train.steps` fixed and no time budget (a budget makes the
step count depend on the machine's speed), on one thread (COLMAP's mapper and torch) so both run in one order, then records the
trained field's checksum (sha256 over its tensors, by name) and the mesh's vertex and face counts. Appends one row per
run to benchmarks/results/same_results.json, keyed by the commit, so two commits' rows can be compared:

    python benchmarks/same_results.py            # run at this commit, append its row
    python benchmarks/same_results.py --check    # also fail (exit 1) unless every row has the same results
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "benchmarks" / "results" / "same_results.json"


def field_checksum(field: Path) -> str:
    """sha256 over the field's tensors in name order (the pickle's own bytes carry nothing but the same numbers)."""
    import torch

    state = torch.load(field, map_location="cpu", weights_only=True)["state_dict"]
    h = hashlib.sha256()
    for name in sorted(state):
        h.update(name.encode())
        h.update(state[name].detach().contiguous().numpy().tobytes())
    return h.hexdigest()


def mesh_counts(ply: Path) -> tuple[int, int]:
    import trimesh

    mesh = trimesh.load(ply, force="mesh", process=False)
    return len(mesh.vertices), len(mesh.faces)


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def provenance() -> dict:
    """Commit, machine and load (what benchmarks/README.md asks of every record), without importing recon: the script
    runs unchanged against any commit's tree."""
    import torch

    return {"commit": _git("rev-parse", "HEAD"), "uncommitted_changes": bool(_git("status", "--porcelain", "--untracked-files=no")),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": {"cpu_count": os.cpu_count(), "system": platform.system(), "python": platform.python_version(),
                        "torch": torch.__version__},
            "load_average_start": [round(x, 2) for x in os.getloadavg()]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--check", action="store_true", help="exit 1 unless all rows of the record agree")
    args = parser.parse_args()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    where = provenance()
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "scene"
        cmd = [sys.executable, "-c", "from recon.app.cli import main; main()", "run", str(ROOT / "fixtures/sample/images"),
               "--out", str(scene), "--preset", "fast", "--set", f"train.steps={args.steps}", "--set", "train.budget=",
               "--set", "train.seed=0", "--set", "poses.num_threads=1"]
        subprocess.run(cmd, check=True, env=env, cwd=ROOT)
        vertices, faces = mesh_counts(scene / "04_mesh" / "mesh.ply")
        metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
        row = {**where, "steps": metrics["steps"], "threads": 1, "rays_per_s": metrics["rays_per_s"],
               "psnr": metrics["test"]["psnr"], "field_sha256": field_checksum(scene / "03_field" / "field.pt"),
               "mesh_vertices": vertices, "mesh_faces": faces}
    rows = json.loads(RECORD.read_text()) if RECORD.exists() else []
    rows.append(row)
    RECORD.write_text(json.dumps(rows, indent=1) + "\n")
    print(json.dumps(row, indent=1))
    if args.check:
        keys = {(r["steps"], r["field_sha256"], r["mesh_faces"]) for r in rows if r["steps"] == args.steps}
        if len(keys) > 1:
            print(f"different results across commits: {sorted(keys)}", file=sys.stderr)
            return 1
        print(f"same field checksum and mesh face count in all {len(rows)} rows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
