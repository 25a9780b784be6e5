"""`recon bench`: run presets on a data set and measure the trade — wall time vs held-out PSNR vs mesh error.

Each preset runs the real pipeline in its own scene folder (poses and normalize are computed once and
reused through the stage cache), then the table (Markdown), the raw numbers (JSON) and a PNG of
held-out PSNR against training time, one curve per preset, are written to the output folder.
Every row carries its provenance (commit, machine, device, load average, date): speed numbers from different
commits, machines or loads do not compare. A benchmark measures; it asserts nothing.
"""
from __future__ import annotations

import contextlib
import json
import os
import platform
import shutil
import subprocess
import time
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

from rich.markup import escape

from recon.app.progress import Reporter
from recon.atomic import read_json, write_bytes_atomic, write_json_atomic
from recon.config import load_config
from recon.errors import ReconError

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared" / "data"
DATASETS = {
    "sample": (REPO / "fixtures" / "sample" / "images", REPO / "fixtures" / "sample" / "gt_mesh.ply"),
    "lego-half": (SHARED / "nerf_synthetic_lego_half", None),
    "fox": (SHARED / "fox" / "images", None),
}
GENERATED = {"tabletop_realistic": ("gen_tabletop", {}), "tabletop_turntable": ("gen_tabletop", {"turntable": True}),
             "tabletop_sweep": ("gen_tabletop", {"turntable": True, "backdrop": True}),
             "tabletop_closeups": ("gen_tabletop", {"closeups": True}),
             "wall_mounted": ("gen_tabletop", {"mounted": True, "closeups": True}),
             "tabletop_painted": ("gen_tabletop", {"painted": True}),
             "tabletop_far": ("gen_tabletop", {"far": True}),
             "tabletop_video": ("gen_video", {})}
"""Data sets rendered on first use (then cached) by fixtures/<generator>.py's `bench_dataset` (with these keyword
arguments): photos (or a video) without masks.
``NAME@SEED`` renders the same capture from another seed (other camera path, textures, exposures and noise).
``tabletop_far`` is the realistic tabletop photographed from further back: a small object with things beside it on the
table, where the object region must leave the clutter out and the object train larger than the preset's photos
(benchmarks/results/tabletop_far_fast.json)."""


def _generated_dataset(name: str) -> tuple[Path, Path]:
    """Render (once) a generated data set into the user cache: its photos folder and its true mesh."""
    import importlib.util
    import sys

    base, _, seed = name.partition("@")
    if seed and not seed.isdigit():
        raise ReconError(f"Benchmark data '{name}': the part after '@' is the generator's seed, a whole number "
                         f"(e.g. {base}@2).")
    generator, kwargs = GENERATED[base]
    script = REPO / "fixtures" / f"{generator}.py"
    if not script.is_file():
        raise ReconError(f"Benchmark data '{name}' is rendered by {script}, which this installation lacks; "
                         f"run recon bench from a source checkout.")
    module_name = f"_recon_fixture_{generator}"
    module = sys.modules.get(module_name)
    if module is None:
        spec = importlib.util.spec_from_file_location(module_name, script)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module  # its dataclasses look their module up while it loads
        spec.loader.exec_module(module)
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "recon" / "datasets" / name
    return module.bench_dataset(cache, **kwargs, **({"seed": int(seed)} if seed else {}))


def resolve_dataset(name: str) -> tuple[Path, Path | None]:
    if name.partition("@")[0] in GENERATED:
        return _generated_dataset(name)
    if name in DATASETS:
        source, gt = DATASETS[name]
    else:
        source, gt = Path(name), None
    if not source.exists():
        known = ", ".join([*DATASETS, *GENERATED])
        raise ReconError(f"Benchmark data '{name}' not found at {source}. Known: {known} or a path.")
    return source, gt if gt is not None and gt.exists() else None


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def load_average() -> list[float] | None:
    """The host's 1/5/15-minute load average, rounded (None where the OS does not say): other jobs slow every rate
    a record holds."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):  # not on every platform
        return None


def _cpu_model() -> str:
    """The CPU's model name where the OS says it (Linux), else its architecture."""
    with contextlib.suppress(OSError):  # no /proc (not Linux): the architecture below
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _cpu_vectors() -> str | None:
    """The widest vector instructions torch's CPU kernels use here ("AVX2", "AVX512", ...), recorded beside the model
    name because one model name covers CPUs of different speed (benchmarks/results/*_profile_cpu.json): rows compare
    only where both match."""
    import torch

    with contextlib.suppress(AttributeError, RuntimeError):
        return str(torch.backends.cpu.get_cpu_capability())
    return None


RECORDS = "benchmarks/results"
"""Where the committed benchmark records live, relative to the checkout."""


def _stage_summary(scene: Path, stage: str) -> dict[str, Any]:
    """What a stage of `scene` reported when it ran (its manifest's summary), or {} when the manifest lacks it."""
    try:
        return json.loads((scene / "manifest.json").read_text())["stages"][stage].get("summary") or {}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def provenance() -> dict[str, Any]:
    """The commit and machine a measurement ran on: what a reader needs to tell whether two numbers compare. Changes
    under ``RECORDS`` do not count as uncommitted: a record one command writes changes no code that the next one
    measures."""
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", f":(exclude){RECORDS}")
    try:
        torch_version: str | None = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = None
    return {
        "commit": _git("rev-parse", "HEAD"),
        "uncommitted_changes": bool(status) if status is not None else None,
        "machine": {
            "cpu_count": os.cpu_count(),
            "cpu": _cpu_model(),
            "cpu_vectors": _cpu_vectors(),
            "system": platform.system(),
            "python": platform.python_version(),
            "torch": torch_version,
        },
    }


REPORT_FILES = ("bench.json", "bench.md", "bench.png", "bench_accuracy.png", "bench_meshes.png", "profile.md",
                "profile.json")
"""What `recon bench` (and `--profile`) writes at the top of its --out folder, beside one scene folder a preset."""


def claim_bench_folder(out_dir: Path) -> None:
    """Check that `recon bench` may write into `out_dir` (recon.runner.ownership), before anything runs: a new or empty
    folder or an earlier benchmark's, where a file of the user's in the place of a report is refused, never replaced.
    The scenes inside are recon scenes, which the pipeline itself will only reuse, never replace."""
    from recon.runner.ownership import claim_names
    from recon.stages import scene_parts

    claim_names(out_dir, "bench", scene_parts, REPORT_FILES, _unrecorded_bench)


def _is_profile_json(data: Any) -> bool:
    """Whether `data` is a profile.json `recon bench --profile` writes: rows with a preset's name, the machine's limits
    and the steps profiled, or the {"limits", "results"} form without provenance, which older checkouts write; a
    folder holding either is recon's to replace."""
    if isinstance(data, dict):
        return {"limits", "results"} <= data.keys()
    return (isinstance(data, list) and bool(data)
            and all(isinstance(r, dict) and {"name", "limits", "profiled_steps"} <= r.keys() for r in data))


def _unrecorded_bench(folder: Path) -> set[str] | None:
    """The reports of a benchmark folder without a record, when it holds nothing else but recon scenes (a
    manifest.json each) and its bench.json (rows with a preset's name, PSNR and commit) or profile.json is recon's."""
    rows: Any = None
    with contextlib.suppress(OSError, ValueError):
        rows = read_json(folder / "bench.json") if (folder / "bench.json").is_file() else None
    ours = isinstance(rows, list) and bool(rows) and all(isinstance(r, dict) and {"name", "psnr", "commit"} <= r.keys()
                                                         for r in rows)
    profile: Any = None
    with contextlib.suppress(OSError, ValueError):
        profile = read_json(folder / "profile.json") if (folder / "profile.json").is_file() else None
    ours = ours or _is_profile_json(profile)
    entries = list(folder.iterdir())
    if not ours or not all(p.name in REPORT_FILES and p.is_file() and not p.is_symlink()
                           or p.is_dir() and not p.is_symlink() and (p / "manifest.json").is_file() for p in entries):
        return None
    return {p.name for p in entries if p.name in REPORT_FILES}


def prepare_scene(data: str, out_dir: Path, config: Any, report: Reporter) -> Path:
    """Poses and normalize of `data` in `out_dir/<name>-poses` (cached): the scene every preset starts from."""
    from recon.stages import default_pipeline

    source, _ = resolve_dataset(data)
    out_dir.mkdir(parents=True, exist_ok=True)
    base = out_dir / f"{Path(data).name}-poses"
    default_pipeline().run(base, config, report, source=source.resolve(), until_stage="normalize")
    return base


def run_bench(
    data: str,
    presets: list[str],
    out_dir: Path,
    overrides: list[str],
    report: Reporter,
    until: str = "mesh",
) -> list[dict[str, Any]]:
    """Run every preset on `data`; write bench.md, bench.json, bench.png (and, with meshes, bench_accuracy.png
    and bench_meshes.png) into `out_dir`."""
    from recon.stages import default_pipeline

    source, gt = resolve_dataset(data)
    claim_bench_folder(out_dir)
    pipeline = default_pipeline()
    where = provenance()
    t0 = time.perf_counter()
    base = prepare_scene(data, out_dir, load_config(None, overrides), report)
    prepare_wall = time.perf_counter() - t0
    rows = []
    for preset in presets:
        scene = preset_scene(out_dir, data, preset)
        if not scene.exists():  # start from the shared poses/normalize
            shutil.copytree(base, scene, ignore=shutil.ignore_patterns(".lock", ".work"))
        config = load_config(preset, overrides)
        report.info(f"[bold]benchmark: {escape(preset)}[/] on {escape(data)}", markup=True)
        load_start = load_average()
        t0 = time.perf_counter()
        # poses/normalize: cached from the shared copy unless this preset changes their options; train (and
        # mesh) always run, so every preset's time is measured
        outcomes = pipeline.run(scene, config, report, source=source.resolve(), until_stage="normalize", preset=preset)
        outcomes += pipeline.run(scene, config, report, source=source.resolve(), from_stage="train", until_stage=until,
                                 preset=preset)
        wall = time.perf_counter() - t0
        metrics = json.loads((scene / "03_field" / "metrics.json").read_text())
        row: dict[str, Any] = {
            "name": preset,
            "data": data,
            "overrides": list(overrides),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            **where,
            "device": metrics.get("device"),
            "load_average_start": load_start,  # the host's 1/5/15-minute load: other jobs slow every rate measured
            "load_average_end": load_average(),
            "poses_normalize_wall_s": round(prepare_wall, 1),  # shared by every preset; cached on a rerun
            "model": metrics["model"],
            "steps": metrics["steps"],
            "train_time_s": metrics["train_time_s"],
            "wall_s": round(wall, 1),
            "stage_wall_s": {o.name: round(o.wall_s, 1) for o in outcomes if o.action == "ran"},
            "psnr": round(metrics["test"]["psnr"], 2),
            "ssim": round(metrics["test"]["ssim"], 4),
            # each photo's colours fitted on its left half, its right half scored: comparable whether or not the
            # field modelled the photos' exposure (with per-photo appearance it is the psnr itself)
            "psnr_fitted": _psnr_fitted(metrics["test"]),
            "test_views": len(metrics["test"]["views"]),
            "rays_per_s": metrics["rays_per_s"],
            "evals": metrics["evals"],
            # how the fast field started: inside the masks' visual hull (train.hull_start), or empty with silhouettes
            # and so culling slowly (FastConfig.slow_occupancy_alpha_start) and smoothing plain faces (train.smoothness)
            "hull_start": metrics.get("hull_start"),
            "slow_culling": metrics.get("slow_culling"),
            "smoothness": metrics.get("smoothness"),
        }
        normalized = _stage_summary(scene, "normalize")
        row["auto_masks"] = normalized.get("auto_masks")
        row["auto_masks_in_hull"] = normalized.get("auto_masks_in_hull")
        report_path = scene / "04_mesh" / "mesh_report.json"
        if until == "mesh" and report_path.is_file():  # how whole the mesh is, with or without a true surface
            coherence = json.loads(report_path.read_text()).get("coherence", {})
            pieces, projected = coherence.get("largest_piece", {}), coherence.get("projected", {})
            row["mesh_pieces"] = pieces.get("pieces")
            row["mesh_largest_piece_area"] = _rounded(pieces.get("largest_area_fraction"))
            row["mesh_coverage"] = _rounded(projected.get("coverage"))
            row["mesh_points_missing"] = _rounded(coherence.get("points", {}).get("missing"))
        if until == "mesh" and gt is not None:
            from recon.evaluation.mesh_eval import compare_to_gt

            acc = compare_to_gt(scene, gt)
            row["fscore_1pct"] = acc.get("fscore@0.01")
            row["chamfer_rel"] = acc.get("chamfer_l1_rel")
            row["fscore_05pct"] = acc.get("fscore@0.005")
            row["normal_consistency"] = acc.get("normal_consistency")
            row["fscore_seen_1pct"] = acc.get("fscore_seen@0.01")  # where the photos can see (`seen_by`)
            row["precision_seen_1pct"] = acc.get("precision_seen@0.01")
            row["mesh_observable_share"] = acc.get("pred_observable_share")
            row["pose_residual_rms_rel"] = acc.get("alignment", {}).get("residual_rms_rel")
            if (gt.parent / "masks").is_dir():  # true object masks beside the truth: score the cut-outs too
                from recon.evaluation.mesh_eval import silhouette_iou
                from recon.runner.pipeline import recorded_source

                cut = silhouette_iou(scene, gt.parent / "masks", recorded_source(scene))
                row["capture"] = json.loads((scene / "02_scene" / "scene.json").read_text()).get("capture")
                for key, name in (("mean_iou", "silhouette_iou"), ("min_iou", "silhouette_iou_min"),
                                  ("mean_masks_iou", "masks_iou"), ("min_masks_iou", "masks_iou_min")):
                    if key in cut:
                        row[name] = round(cut[key], 4)
        rows.append(row)
        write_results(rows, out_dir, data)
    return rows


def preset_scene(out_dir: Path, data: str, preset: str) -> Path:
    """The scene folder a benchmark makes for one preset."""
    return out_dir / f"{Path(data).name}-{preset}"


def _db(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f} dB"


def _psnr_fitted(test: dict[str, Any]) -> float | None:
    """The test PSNR with each photo's colours fitted on its left half (`recon.evaluation.views.evaluate`)."""
    if "psnr_fitted" in test:
        return round(test["psnr_fitted"], 2)
    return round(test["psnr"], 2) if "psnr_neutral" in test else None  # per-photo appearance: the psnr is that


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)


def write_results(rows: list[dict[str, Any]], out_dir: Path, data: str) -> None:
    from recon.plots import accuracy_plot, mesh_sheet, tradeoff_plot

    write_json_atomic(out_dir / "bench.json", rows)
    has_mesh = any("fscore_1pct" in r for r in rows)
    has_pieces = any(r.get("mesh_pieces") is not None for r in rows)
    lines = [
        f"# recon bench — {data}",
        "",
        "| preset | model | steps | train time | wall (train+mesh) | test PSNR | colours fitted | SSIM | views | rays/s |"
        + (" F-score@1% | Chamfer-L1 / diag | F-score@0.5% | normal agreement |" if has_mesh else "")
        + (" mesh pieces | largest piece's area |" if has_pieces else ""),
        "|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|" if has_mesh else "")
        + ("---|---|" if has_pieces else ""),
    ]
    for r in rows:
        line = (
            f"| {r['name']} | {r['model']} | {r['steps']} | {r['train_time_s']:.0f} s | {r['wall_s']:.0f} s | "
            f"{r['psnr']:.2f} dB | {_db(r.get('psnr_fitted'))} | {r['ssim']:.3f} | {r['test_views']} | "
            f"{r['rays_per_s']:,.0f} |"
        )
        if has_mesh:
            f1, ch = r.get("fscore_1pct"), r.get("chamfer_rel")
            line += f" {f1:.3f} |" if f1 is not None else " — |"
            line += f" {100 * ch:.2f}% |" if ch is not None else " — |"
            f05, nc = r.get("fscore_05pct"), r.get("normal_consistency")
            line += f" {f05:.3f} |" if f05 is not None else " — |"
            line += f" {nc:.3f} |" if nc is not None else " — |"
        if has_pieces:
            pieces, largest = r.get("mesh_pieces"), r.get("mesh_largest_piece_area")
            line += f" {pieces} |" if pieces is not None else " — |"
            line += f" {largest:.1%} |" if largest is not None else " — |"
        lines.append(line)
    lines += ["", *provenance_lines(rows), "", "![PSNR vs time](bench.png)", ""]
    if has_mesh:  # one point per preset: the mesh's accuracy against its training time
        lines += ["![mesh accuracy vs time](bench_accuracy.png)", ""]
        accuracy_plot(rows, out_dir / "bench_accuracy.png", title=f"mesh F-score vs training time — {data}")
    meshes = [(_mesh_caption(r), preset_scene(out_dir, data, r["name"]) / "04_mesh" / "preview_front.png")
              for r in rows]
    meshes = [(caption, preview) for caption, preview in meshes if preview.is_file()]
    if meshes:  # each preset's mesh from the same camera
        lines += ["![each preset's mesh](bench_meshes.png)", ""]
        mesh_sheet(meshes, out_dir / "bench_meshes.png")
    write_bytes_atomic(out_dir / "bench.md", "\n".join(lines))
    tradeoff_plot(rows, out_dir / "bench.png", title=f"held-out PSNR vs training time — {data}")


def _mesh_caption(row: dict[str, Any]) -> str:
    """A preset's name and training time, with its mesh's F-score and pieces where the row has them."""
    details = []
    if row.get("fscore_05pct") is not None:
        details.append(f"F@0.5% {row['fscore_05pct']:.3f}")
    if row.get("mesh_pieces") is not None:
        details.append(f"{row['mesh_pieces']} piece{'' if row['mesh_pieces'] == 1 else 's'}")
    return f"{row['name']}: {row['train_time_s'] / 60:.1f} min" + ("\n" + ", ".join(details) if details else "")


def machine_name(machine: dict[str, Any]) -> str:
    """A provenance record's CPU as a reader compares it: its model name and, where recorded, its vector unit."""
    vectors = machine.get("cpu_vectors")
    return f"{machine.get('cpu') or 'an unnamed CPU'}" + (f", {vectors}" if vectors else "")


def provenance_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per row saying where and when it ran (rows without a machine record are left out)."""
    lines = []
    for r in rows:
        machine = r.get("machine")
        if not machine:
            continue
        load = r.get("load_average_start") or []
        commit = (r.get("commit") or "unknown")[:12] + (" + uncommitted changes" if r.get("uncommitted_changes") else "")
        lines.append(f"- {r['name']}: commit {commit}, {r.get('date', '?')}, {machine.get('cpu_count')} CPUs "
                     f"({machine_name(machine)}), torch {machine.get('torch')}, device {r.get('device')}, load average "
                     f"{load[0] if load else '?'} at the start")
    return lines
