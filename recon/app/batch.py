"""`recon batch`: many captures at once, each one a Ray task running the same staged, cached pipeline.

Ray does the scheduling: every capture is a task that asks for the CPUs, GPU and memory its config needs, so
Ray packs as many captures onto each node as fit. A task runs `Pipeline.run` into `OUT/<capture name>/`
exactly as `recon run` would, so a re-run batch (or a task Ray retries after its worker died) resumes each
capture from its cache. A capture that fails records its error and the others go on; `OUT/batch.md` and
`OUT/batch.json` sum up this batch's captures, then those only earlier batches into OUT ran.

OUT follows recon's ownership rule (`recon.runner.ownership`): its `.recon-batch.json` records which capture each folder
holds, so a capture keeps its folder across batches and another capture of the same name gets name-2 instead of
replacing it.
"""
from __future__ import annotations

import math
import os
import re
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from recon.app.progress import Reporter, format_seconds
from recon.atomic import read_json, write_bytes_atomic, write_json_atomic
from recon.config import RunConfig, load_config
from recon.errors import InputError, ReconError
from recon.runner.ownership import OwnedFolder, claim_folder, resolve_path
from recon.runner.pipeline import MANIFEST, prepare_scene_dir

INSTALL_HINT = 'pip install -c constraints.txt -e ".[ray]"'
GENERIC_NAMES = {"images", "image", "photos", "imgs", "rgb", "input", "frames"}
"""Photo folder names that say nothing about the capture: such a capture is named after the folder above."""
STAGES = ("poses", "normalize", "train", "mesh")
REPORT_FILES = ("batch.md", "batch.json")
"""The files `recon batch` writes into OUT itself (each capture's scene folder is its own, with its manifest)."""
PROCESS_BASE_MB = 2048
"""Memory a capture's process needs besides the mesh's density grid: torch, pycolmap, photos, the model (a
half-resolution Lego's mesh stage at 384³ stays under it)."""


@dataclass
class Capture:
    """One capture of a batch: where its photos (or poses) are and the folder name it gets under OUT."""

    name: str
    source: Path
    error: str | None = None
    """Known before anything runs (e.g. the path does not exist): the capture is recorded as failed."""


@dataclass
class Resources:
    """What each capture's Ray task asks for, and why (printed before the batch starts)."""

    num_cpus: float
    num_gpus: float
    memory_mb: int
    reasons: list[str] = field(default_factory=list)

    def per_node(self, node: dict[str, float]) -> int:
        """How many captures fit at once on a node with these Ray resources (CPU, GPU, memory in bytes)."""
        fits = [node.get("CPU", 0) / self.num_cpus, node.get("memory", 0) / (self.memory_mb * 2**20)]
        if self.num_gpus:
            fits.append(node.get("GPU", 0) / self.num_gpus)
        return int(math.floor(min(fits) + 1e-9))


def require_ray() -> Any:
    """The ray module, or a ReconError that says how to install it (it is an optional extra)."""
    try:
        import ray
    except ImportError:
        raise ReconError(f"`recon batch` runs captures on Ray, which is not installed. Install it with: {INSTALL_HINT}") from None
    return ray


# --- inputs → captures -------------------------------------------------------------------------------------


def expand_inputs(inputs: list[Path]) -> list[Capture]:
    """Capture folders, videos or poses files, or one text file listing them (one per line, # comments).

    Relative paths in a list file are read relative to the list file. The same path given twice is one
    capture. Each capture is named after its folder (or the folder above a generic `images/`); equal names
    get -2, -3, ... in input order, so the same inputs always map to the same output folders.
    """
    if not inputs:
        raise InputError("Give `recon batch` at least one capture folder (or a text file listing them).")
    paths: list[Path] = []
    for item in inputs:
        if item.is_file() and item.suffix.lower() in (".txt", ".lst", ".list"):
            paths += _read_list(item)
        else:
            paths.append(item)
    seen: set[Path] = set()
    unique: list[tuple[Path, Path]] = []
    for p in paths:
        key = resolve_path(p, "The capture")
        if key not in seen:
            seen.add(key)
            unique.append((p, key))
    used: set[str] = set()
    captures = []
    for p, resolved in unique:
        name = _free_name(capture_name(p), used)
        used.add(name)
        error = None if p.exists() else f"The input {p} does not exist. Fix the path (or remove it from the list)."
        captures.append(Capture(name, resolved, error))
    return captures


def _free_name(base: str, taken: set[str]) -> str:
    """`base`, or the first of base-2, base-3, ... not in `taken`."""
    name, k = base, 1
    while name in taken:
        k += 1
        name = f"{base}-{k}"
    return name


def place_captures(captures: list[Capture], owned: OwnedFolder) -> list[str]:
    """Give each capture its folder in OUT without taking one that holds another capture; record them in OUT's record.

    A capture that an earlier batch into OUT already ran keeps its folder (so it resumes); any other gets its own
    name, or name-2, name-3, ... when that folder holds a different capture (or something that is not recon's).
    Returns one line per capture whose name was taken, saying where it goes instead.
    """
    raw = owned.record.get("captures")
    recorded: dict[str, str] = {k: v for k, v in raw.items() if isinstance(v, str)} if isinstance(raw, dict) else {}
    folder_of = {source: name for name, source in recorded.items()}
    holders = dict(recorded)  # folder name → the capture in it ("" for something in OUT that is no capture of a batch)
    for entry in owned.path.iterdir() if owned.path.is_dir() else ():
        holders.setdefault(entry.name, "")
    notes = []
    for c in captures:
        if str(c.source) in folder_of:
            c.name = folder_of[str(c.source)]
            continue
        base = capture_name(c.source)
        c.name = _free_name(base, set(holders))
        if c.name != base:
            held = f"holds {holders[base]}" if holders[base] else "is not a capture folder of recon batch"
            notes.append(f"{c.source} → {owned.path / c.name}: {owned.path / base} {held}")
        holders[c.name] = str(c.source)
        if not c.error:
            recorded[c.name] = str(c.source)
    owned.record["captures"] = recorded
    return notes


def _read_list(path: Path) -> list[Path]:
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"Cannot read the capture list {path}: {exc}. Give a text file with one path per line.") from None
    entries = [line.split("#", 1)[0].strip() for line in lines]
    paths = [Path(e) if Path(e).is_absolute() else path.parent / e for e in entries if e]
    if not paths:
        raise InputError(f"The capture list {path} names no capture (one path per line; # starts a comment).")
    return paths


def capture_name(path: Path) -> str:
    """Folder-safe name of a capture: `shoe/images` → shoe, `vase.mp4` → vase, `lego/transforms.json` → lego."""
    path = Path(os.path.normpath(path.absolute()))
    stem = path.stem if path.suffix else path.name
    if stem.lower() in GENERIC_NAMES or (path.suffix.lower() in (".json", ".bin", ".txt") and path.parent.name):
        stem = path.parent.name
    return re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("._") or "capture"


# --- resources ---------------------------------------------------------------------------------------------


def task_resources(config: RunConfig, cluster: dict[str, float], cpus_per_capture: float | None = None) -> Resources:
    """CPUs, GPU and memory one capture asks Ray for, derived from its config (each with its reason)."""
    reasons = []
    device = config.train.device.strip().lower()
    gpus = cluster.get("GPU", 0)
    if device.startswith("cuda"):
        num_gpus = 1.0
        reasons.append(f"1 GPU: train.device={config.train.device}")
    elif device == "auto" and gpus > 0:
        num_gpus = 1.0
        reasons.append(f"1 GPU: train.device=auto and the cluster has {gpus:g} GPU(s), so training runs on CUDA")
    else:
        num_gpus = 0.0
        reasons.append(f"no GPU: train.device={config.train.device}" + ("" if device == "cpu" else " and the cluster has no GPU"))
    if cpus_per_capture is not None:
        num_cpus = float(cpus_per_capture)
        reasons.append(f"{num_cpus:g} CPU(s): --cpus-per-capture")
    elif config.poses.num_threads > 0:
        num_cpus = float(config.poses.num_threads)
        reasons.append(f"{num_cpus:g} CPU(s): poses.num_threads={config.poses.num_threads} (training gets as many threads)")
    elif num_gpus:
        num_cpus = 2.0
        reasons.append("2 CPUs: the GPU trains; the CPU runs SfM and feeds it (the rest of a node's CPUs serve its other GPUs)")
    else:
        num_cpus = 1.0
        reasons.append(
            "1 CPU: CPU training; one thread per capture and one capture per core gives the most captures per hour "
            "(docs/batch.md); set --cpus-per-capture N for fewer, faster captures (time-budget presets train more steps)"
        )
    res = config.mesh.resolution or config.mesh.max_resolution
    grid_mb = min(config.mesh.memory_budget_mb, math.ceil(res**3 * 4 / 2**20))
    memory_mb = grid_mb + PROCESS_BASE_MB
    reasons.append(f"{memory_mb} MB memory: a {res}³ density grid ({grid_mb} MB, capped by mesh.memory_budget_mb) + {PROCESS_BASE_MB} MB for the process")
    return Resources(num_cpus, num_gpus, memory_mb, reasons)


# --- one capture (runs inside a Ray worker) ----------------------------------------------------------------


class _CaptureReporter(Reporter):
    """Writes the capture's log and remembers which stages ran or were cached; tells the board each stage."""

    def __init__(self, console: Any, board: Any, name: str):
        super().__init__(console)
        self.board, self.name = board, name
        self.actions: dict[str, dict] = {}

    def stage_start(self, name: str) -> None:
        super().stage_start(name)
        if self.board is not None:
            self.board.update.remote(self.name, name)

    def stage_cached(self, name: str, summary: dict) -> None:
        super().stage_cached(name, summary)
        self.actions[name] = {"action": "cached", "wall_s": 0.0}

    def stage_done(self, name: str, wall_s: float, summary: dict) -> None:
        super().stage_done(name, wall_s, summary)
        self.actions[name] = {"action": "ran", "wall_s": round(wall_s, 2)}


def run_capture(source: Path, scene_dir: Path, preset: str, overrides: list[str], board: Any = None) -> dict[str, Any]:
    """Run the pipeline on one capture, as `recon run SOURCE --out SCENE_DIR` would; never raises a ReconError.

    The stage output goes to SCENE_DIR/batch.log; an error (user-fixable or a bug) is returned in the record.
    """
    from rich.console import Console

    from recon.stages import default_pipeline

    name = scene_dir.name
    t0 = time.perf_counter()
    record: dict[str, Any] = {"name": name, "source": str(source), "folder": str(scene_dir), "pid": os.getpid()}
    if board is not None:
        board.update.remote(name, "starting")
    reporter = None
    try:
        prepare_scene_dir(scene_dir)
        with open(scene_dir / "batch.log", "a") as log:
            reporter = _CaptureReporter(Console(file=log, width=160, highlight=False), board, name)
            reporter.info(f"recon batch: {source} → {scene_dir} (preset {preset}, pid {os.getpid()})")
            try:
                default_pipeline().run(scene_dir, load_config(preset, overrides), reporter, source=source, preset=preset)
            except ReconError as exc:
                reporter.console.print(f"error: {exc}")
                record["error"] = str(exc)
            except Exception as exc:  # a bug in recon: keep the traceback with the capture, the batch goes on
                log.write("".join(traceback.format_exception(exc)))
                record["error"] = f"internal error: {type(exc).__name__}: {exc} (traceback in {scene_dir / 'batch.log'})"
    except ReconError as exc:  # the output folder itself is unusable
        record["error"] = str(exc)
    record["wall_s"] = round(time.perf_counter() - t0, 2)
    if reporter is not None and reporter.warnings:  # batch.md shows them: nobody reads a hundred batch.logs
        record["warnings"] = list(reporter.warnings)
    record.update(capture_facts(scene_dir, reporter.actions if reporter else {}))
    if board is not None:
        board.update.remote(name, None)
    return record


def capture_facts(scene_dir: Path, actions: dict[str, dict]) -> dict[str, Any]:
    """Per stage ran/cached and time, and the numbers batch.md shows, read from the capture's manifest."""
    import json

    try:
        stages = json.loads((scene_dir / MANIFEST).read_text()).get("stages", {})
    except (OSError, ValueError, AttributeError):
        stages = {}
    facts: dict[str, Any] = {"stages": {}}
    for stage in STAGES:
        entry = stages.get(stage) or {}
        row = {"status": entry.get("status", "missing"), "wall_s": entry.get("wall_s"), "finished": entry.get("finished")}
        row.update(actions.get(stage, {"action": "not run"}))
        facts["stages"][stage] = row
    poses = (stages.get("poses") or {}).get("summary", {})
    if "registered" in poses:
        facts["photos"] = f"{poses['registered']}/{poses['total']}"
    elif "cameras" in poses:
        facts["photos"] = f"{poses['cameras']} (poses given)"
    train = (stages.get("train") or {}).get("summary", {})
    if "psnr" in train:
        facts["psnr"] = train["psnr"]
    mesh = (stages.get("mesh") or {}).get("summary", {})
    if "faces" in mesh:
        facts["faces"], facts["vertices"] = mesh["faces"], mesh["vertices"]
    return facts


# --- the driver --------------------------------------------------------------------------------------------


def start_ray(address: str | None) -> Any:
    """Join the cluster at `address` ("auto" or HOST:PORT), or start Ray on this machine; reuse a live connection.

    Workers get this recon on their PYTHONPATH (on a cluster: a path all nodes see, like the outputs); Ray itself
    sets OMP_NUM_THREADS to each task's CPUs, which recon's torch honors. OpenMP keeps its default wait policy: a
    task's threads have their CPUs to themselves, and sleeping between torch's operations (OMP_WAIT_POLICY=PASSIVE)
    made a training step markedly longer (benchmarks/results/sample_omp_wait_policy.json).
    A Ray started here listens on loopback only (`_init_on_loopback`): joining a cluster is always explicit.
    """
    import logging

    ray = require_ray()
    if ray.is_initialized():
        return ray
    code = str(Path(__file__).resolve().parents[2])
    env = {"PYTHONPATH": os.pathsep.join(p for p in (code, os.environ.get("PYTHONPATH", "")) if p)}
    kwargs: dict[str, Any] = {"runtime_env": {"env_vars": env}, "logging_level": logging.WARNING, "log_to_driver": False}
    if address and not _is_loopback(address):
        ray.init(address=address, **kwargs)
    elif address:  # a Ray on this machine (like the one a local batch starts): join it on loopback too
        _init_on_loopback(ray, address=address, **kwargs)
    else:
        _init_on_loopback(ray, num_cpus=len(os.sched_getaffinity(0)), include_dashboard=False, **kwargs)
    return ray


LOOPBACK = "127.0.0.1"


def _is_loopback(address: str) -> bool:
    host = address.rsplit(":", 1)[0].strip("[]") if ":" in address else address
    return host in ("localhost", "::1") or host.startswith("127.")


def _init_on_loopback(ray: Any, **kwargs: Any) -> None:
    """`ray.init` with this node on 127.0.0.1: every server it starts (GCS, raylet, object manager, workers, agents)
    listens on loopback only, and a driver joins a loopback address as given.

    Ray binds its servers to loopback only when the node's address is 127.0.0.1, but on Linux it swaps a given
    127.0.0.1 (also in a cluster address) for the machine's network address unless its clusters are switched off,
    as Ray itself does on macOS and Windows (`ray_constants.ENABLE_RAY_CLUSTER`, read when addresses are resolved).
    Anyone who could reach a server on the network address could join the cluster and run code as the user. The
    switch is flipped only for this call; if Ray still comes up on another address, it is stopped and the batch
    refused.
    """
    from ray._private import ray_constants

    clusters = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(_node_ip_address=LOOPBACK, **kwargs)
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = clusters
    node_ip = ray.util.get_node_ip_address()
    if node_ip != LOOPBACK:
        ray.shutdown()
        raise ReconError(
            f"Ray started on the network address {node_ip} instead of {LOOPBACK}, where other machines could join it "
            f"and run code as you; recon stopped it. This Ray version ({ray.__version__}) starts differently from the "
            f"one recon knows: install the version in constraints.txt, or join a cluster you set up with --address."
        )


def _board_class(ray: Any) -> Any:
    @ray.remote(num_cpus=0)
    class Board:
        """Which stage each running capture is in, for the driver's live view."""

        def __init__(self) -> None:
            self.stage: dict[str, str] = {}

        def update(self, name: str, stage: str | None) -> None:
            if stage is None:
                self.stage.pop(name, None)
            else:
                self.stage[name] = stage

        def snapshot(self) -> dict[str, str]:
            return dict(self.stage)

    return Board


def run_batch(
    inputs: list[Path],
    out: Path,
    preset: str,
    overrides: list[str],
    report: Reporter,
    address: str | None = None,
    retries: int = 2,
    cpus_per_capture: float | None = None,
) -> dict[str, Any]:
    """Run every capture as a Ray task into OUT/<name>/; write OUT/batch.json and OUT/batch.md; return the result.

    A capture's ReconError is recorded and the others go on; a worker that dies is retried by Ray up to
    `retries` times (each retry resumes from the capture's cache).
    """
    from recon.stages import scene_parts

    require_ray()
    config = load_config(preset, overrides)  # a bad option fails here, before Ray starts
    captures = expand_inputs(inputs)
    adopt_unrecorded_batch(out)
    owned = claim_folder(out, "batch", scene_parts, [c.source for c in captures if not c.error])
    renamed = place_captures(captures, owned)
    prepare_scene_dir(owned.path)
    owned.save(REPORT_FILES)  # before any capture runs: a re-run after a crash finds every capture's folder
    ray = start_ray(address)
    resources = task_resources(config, ray.cluster_resources(), cpus_per_capture)
    nodes = [n["Resources"] for n in ray.nodes() if n.get("Alive")]
    per_node = [resources.per_node(n) for n in nodes]
    report.info(
        f"recon batch: {len(captures)} captures, preset {preset}, {len(nodes)} node(s) "
        f"({', '.join(_node_text(n) for n in nodes)})"
    )
    for note in renamed:
        report.info(note)
    report.info(f"each capture asks for: {'; '.join(resources.reasons)}")
    report.info(f"so Ray runs up to {sum(per_node)} captures at once ({' + '.join(map(str, per_node))} per node)")
    if sum(per_node) == 0:
        raise ReconError(
            f"No node can run a capture: each asks for {resources.num_cpus:g} CPUs, {resources.num_gpus:g} GPUs and "
            f"{resources.memory_mb} MB of memory. Lower --cpus-per-capture or mesh.memory_budget_mb, or add larger nodes."
        )
    board = _board_class(ray).remote()
    task = ray.remote(run_capture).options(
        num_cpus=resources.num_cpus, num_gpus=resources.num_gpus, memory=resources.memory_mb * 2**20,
        max_retries=retries, retry_exceptions=False,
    )
    t0 = time.perf_counter()
    records: dict[str, dict] = {}
    pending: dict[Any, Capture] = {}
    for c in captures:
        if c.error:
            records[c.name] = {"name": c.name, "source": str(c.source), "folder": str(out / c.name), "error": c.error, "stages": {}}
        else:
            pending[task.remote(c.source, out / c.name, preset, overrides, board)] = c
    with report.task("captures", total=len(captures)) as bar:
        bar.update(completed=len(records))
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                c = pending.pop(ref)
                try:
                    records[c.name] = ray.get(ref)
                except ray.exceptions.RayError as exc:  # the worker died more than `retries` times, or Ray failed
                    records[c.name] = {"name": c.name, "source": str(c.source), "folder": str(out / c.name), "stages": {},
                                       "error": f"Ray gave up after {retries} retries: {type(exc).__name__}: {_first_line(exc)}"}
                    records[c.name].update(capture_facts(out / c.name, {}))
                    board.update.remote(c.name, None)  # its worker died before saying it stopped
                if records[c.name].get("error"):
                    report.warn(f"{c.name}: {records[c.name]['error']}")
                for warning in records[c.name].get("warnings", []):
                    report.warn(f"{c.name}: {warning}")
                bar.advance()
            running = ray.get(board.snapshot.remote())
            failed = sum(1 for r in records.values() if r.get("error"))
            bar.update(info=f"{len(records) - failed} done · {len(running)} running · {failed} failed   "
                       + ", ".join(f"{k}: {v}" for k, v in sorted(running.items())))
    result = {
        "preset": preset,
        "overrides": overrides,
        "resources": asdict(resources),
        "nodes": len(nodes),
        "wall_s": round(time.perf_counter() - t0, 2),
        "captures": [records[c.name] for c in captures],
    }
    result["failed"] = sum(1 for r in result["captures"] if r.get("error"))
    result["earlier"] = earlier_records(out, {c.name for c in captures})
    write_batch_reports(out, result)
    return result


def adopt_unrecorded_batch(out: Path) -> None:
    """Give a batch folder from before batches kept a record (`.recon-batch.json`) its record, read from its batch.json.

    Only a folder that holds nothing but batch.md, batch.json and the capture folders that batch.json names (each
    inside OUT) is taken as recon's; anything else stays a folder `claim_folder` refuses.
    """
    owned = OwnedFolder(out, "batch")
    if not out.is_dir() or owned.marker.exists():
        return
    try:
        previous = read_json(out / "batch.json")
        rows = [r for r in previous.get("captures", []) if isinstance(r, dict)]
        captures = {r["name"]: r["source"] for r in rows
                    if isinstance(r.get("name"), str) and isinstance(r.get("source"), str) and Path(r.get("folder", "")).parent == out}
    except (OSError, ValueError, AttributeError, TypeError):
        return
    if {p.name for p in out.iterdir()} <= set(REPORT_FILES) | set(captures):
        owned.record["captures"] = captures
        owned.save(REPORT_FILES)


def earlier_records(out: Path, names: set[str]) -> list[dict[str, Any]]:
    """The records of captures that earlier batches into OUT ran and this one did not (from OUT/batch.json)."""
    try:
        previous = read_json(out / "batch.json")
    except (OSError, ValueError):
        return []
    if not isinstance(previous, dict):
        return []
    rows = [r for key in ("captures", "earlier") for r in previous.get(key) or [] if isinstance(r, dict)]
    seen: set[str] = set(names)
    kept = []
    for r in rows:
        if isinstance(r.get("name"), str) and r["name"] not in seen:
            seen.add(r["name"])
            kept.append(r)
    return kept


def _node_text(node: dict[str, float]) -> str:
    gpus = f" + {node['GPU']:g} GPUs" if node.get("GPU") else ""
    return f"{node.get('CPU', 0):g} CPUs{gpus}, {node.get('memory', 0) / 2**30:.0f} GB"


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:300]


def write_batch_reports(out: Path, result: dict[str, Any]) -> None:
    """OUT/batch.json (everything) and OUT/batch.md (a table of this batch's captures, then of those only earlier
    batches into OUT ran), both written atomically."""
    write_json_atomic(out / "batch.json", result)
    ok = len(result["captures"]) - result["failed"]
    table = ["| capture | stages | wall | photos | test PSNR | mesh | error or warnings |", "|---|---|---|---|---|---|---|"]
    lines = [
        f"# recon batch — {ok} of {len(result['captures'])} captures done, {result['failed']} failed",
        "",
        f"Preset `{result['preset']}`" + (f" with `{' '.join(result['overrides'])}`" if result["overrides"] else "")
        + f"; wall time {format_seconds(result['wall_s'])}; each capture asked for "
        f"{result['resources']['num_cpus']:g} CPU, {result['resources']['num_gpus']:g} GPU, {result['resources']['memory_mb']} MB.",
        "",
        *table,
        *map(_report_row, result["captures"]),
    ]
    if result.get("earlier"):
        lines += ["", "## Captures of earlier batches into this folder", "", *table, *map(_report_row, result["earlier"])]
    write_bytes_atomic(out / "batch.md", "\n".join(lines) + "\n")


def _report_row(r: dict[str, Any]) -> str:
    stages = " ".join(f"{s}:{row['action'] if row['status'] == 'done' else row['status']}" for s, row in r.get("stages", {}).items())
    psnr = f"{r['psnr']:.2f} dB" if "psnr" in r else "—"
    mesh = f"{r['faces']:,} faces" if "faces" in r else "—"
    said = r.get("error") or " ".join(f"warning: {w}" for w in r.get("warnings", []))
    said = said.replace("|", "\\|").replace("\n", " ")
    return f"| {r['name']} | {stages} | {format_seconds(r.get('wall_s'))} | {r.get('photos', '—')} | {psnr} | {mesh} | {said} |"
