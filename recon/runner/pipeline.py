"""The stage runner: the one place that owns caching, fingerprints, the manifest and atomic stage folders.

A stage is a name, its upstream stages, its config slice and a function that writes into a fresh
temporary folder. Its fingerprint hashes the upstream stages' output digests, its config slice, its
format version and any outside input it declares (the photos). A stage whose fingerprint matches the
manifest and whose files still match the checksums recorded when they were written is skipped;
anything else re-runs, and so (through the changed digest) does everything downstream of a changed
output. A stage's folder only ever appears complete: it is written as `.tmp-NAME-PID/`, then renamed
into place, and only then is the manifest (itself written atomically) updated.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import signal
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from recon.app.progress import Reporter
from recon.atomic import fault_point, is_temp_name, read_json, sha256_file, write_json_atomic
from recon.config import RunConfig, config_slice
from recon.errors import InputError, ReconError
from recon.runner.ownership import forbidden_reason, overlap_reason, resolve_path, scene_part_reason

MANIFEST = "manifest.json"
LOCK = ".lock"
SCRATCH_NOTE = "scratch.json"
"""A stage's note in its scratch folder on what the scratch holds ({"headline": ...}: a stopped training's step and
time), which `recon status` shows in the stage's row."""
MANIFEST_VERSION = 1


@dataclass
class StageContext:
    """What a stage function gets: where to write, what to read, its config, and a progress reporter."""

    name: str
    folder: str
    """The stage's folder name inside the scene folder (e.g. '01_poses')."""
    out: Path
    """Fresh temporary folder: write every artifact here; it becomes SCENE/<folder> when the stage returns."""
    work: Path
    """Scratch that survives a crash (checkpoints), keyed by the fingerprint less the stage's `scratch_survives`
    fields; removed after success."""
    inputs: dict[str, Path]
    """Upstream stage name → its finished folder."""
    config: Any
    """This stage's config slice (a dataclass)."""
    run_config: RunConfig
    source: Path | None
    """The photos folder or poses file given to `recon run` (recorded in the manifest)."""
    scene_dir: Path
    report: Reporter
    previous: Path | None = None
    """The stage's finished folder when it was made under options that differ from these, but only in
    `scratch_survives` fields (train: the field a longer budget trains on from), else None (also for a forced run of
    the same options: that one starts again). Read it before returning: the new output replaces it."""


@dataclass(frozen=True)
class Stage:
    """One step of the pipeline. `run` returns a short summary dict (shown by the CLI and `recon status`)."""

    name: str
    folder: str
    inputs: tuple[str, ...]
    version: int
    run: Callable[[StageContext], dict]
    needs_source: bool = False
    source_digest: Callable[[Path, Any], str] | None = None
    """Digest of the stage's outside input (e.g. every photo's bytes), part of the fingerprint."""
    source_stat: Callable[[Path], str] | None = None
    """A cheap signature of the same files (names, sizes, modification times), kept in the manifest: `recon status`
    without options compares it and hashes the files only where it differs."""
    scratch_survives: tuple[str, ...] = ()
    """Config fields whose change keeps the stage's scratch (train: a new time budget goes on from the checkpoint
    instead of training again from step 0) and hands the stage its finished output as `StageContext.previous`; the
    stage reads what its scratch or output was made under."""


@dataclass
class StageOutcome:
    name: str
    action: str  # "ran" | "cached"
    wall_s: float
    summary: dict = field(default_factory=dict)


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def folder_files(folder: Path) -> dict[str, dict]:
    """Per-file checksums of a stage folder: recorded at write time, checked before a cached stage is reused."""
    files = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        files[path.relative_to(folder).as_posix()] = {"sha256": sha256_file(path), "size": path.stat().st_size}
    return files


def digest_of(files: dict[str, dict]) -> str:
    return hashlib.sha256(json.dumps(files, sort_keys=True).encode()).hexdigest()


def package_versions() -> dict[str, str]:
    from importlib import metadata

    versions = {"python": sys.version.split()[0]}
    for name in ("recon", "numpy", "torch", "pycolmap", "trimesh", "scikit-image", "opencv-contrib-python-headless"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


MANIFEST_FORMAT = "recon-scene-manifest"

_ENTRY_TYPES: dict[str, tuple[type, ...]] = {
    "status": (str,), "fingerprint": (str,), "output_digest": (str,), "input_digests": (dict,), "files": (dict,),
    "summary": (dict,), "config": (dict, type(None)), "versions": (dict,), "wall_s": (int, float, type(None)),
    "started": (str,), "finished": (str,), "last_error": (str,), "last_attempt": (str,),
}
"""The type of each key a stage's manifest entry may have: anything else means the file was damaged or edited."""


def manifest_problem(data: Any) -> str | None:
    """Why `data` is not a manifest recon wrote (None when it is one)."""
    if not isinstance(data, dict):
        return f"it holds a {type(data).__name__}, not an object"
    if data.get("format", MANIFEST_FORMAT) != MANIFEST_FORMAT or not isinstance(data.get("version"), int):
        return "it has no recon manifest format/version"
    if not isinstance(data.get("stages"), dict):
        return "'stages' is missing or not an object"
    for key in ("source", "source_from_scene", "preset"):
        if not isinstance(data.get(key), (str, type(None))):
            return f"'{key}' is not a string"
    for name, entry in data["stages"].items():
        if not isinstance(entry, dict):
            return f"the entry of stage '{name}' is not an object"
        for key, value in entry.items():
            if key in _ENTRY_TYPES and not isinstance(value, _ENTRY_TYPES[key]):
                return f"stage '{name}': '{key}' has the wrong type ({type(value).__name__})"
    return None


class Manifest:
    """SCENE/manifest.json: per stage, its fingerprint, status, times, versions, outputs and summary.

    A damaged or hand-edited manifest (bad JSON, wrong types) is not trusted: `warning` says so and every
    stage's cache is ignored, as if the scene were new.
    """

    def __init__(self, scene_dir: Path):
        self.path = scene_dir / MANIFEST
        self.data: dict[str, Any] = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "source": None, "stages": {}}
        self.warning: str | None = None
        if self.path.exists():
            try:
                data = read_json(self.path)
                problem = manifest_problem(data)
                if problem:
                    raise ValueError(problem)
                self.data = data
            except (OSError, ValueError) as exc:
                self.warning = f"{self.path} was unreadable ({exc}); every stage's cache is ignored and re-checked."
        version = self.data["version"]
        if not 1 <= version <= MANIFEST_VERSION:  # a newer recon's scene, or a version no recon wrote: never guess
            why = ("a newer recon wrote it: upgrade recon to use this scene" if version > MANIFEST_VERSION else
                   "no recon writes that version, so the file was edited or damaged")
            raise InputError(
                f"{self.path} is manifest version {version}, and this recon reads versions 1 to {MANIFEST_VERSION}; "
                f"{why}, or give --out a new folder."
            )

    @property
    def stages(self) -> dict[str, dict]:
        return self.data["stages"]

    @property
    def source(self) -> Path | None:
        """The input the scene was last run on; where that path is gone but the same path from the scene folder
        (`source_from_scene`) is there, that one: a project folder holding both the photos and the scene moved."""
        recorded = self.data.get("source")
        if not recorded:
            return None
        beside = self.data.get("source_from_scene")
        if not os.path.exists(recorded) and beside and (self.path.parent / beside).exists():
            return Path(os.path.normpath(self.path.parent.absolute() / beside))
        return Path(recorded)

    def record_source(self, source: Path) -> bool:
        """Keep `source` as the scene's input, also as a path from the scene folder; whether that changed anything."""
        try:
            beside: str | None = os.path.relpath(source.absolute(), self.path.parent.absolute())
        except ValueError:  # another drive
            beside = None
        before = (self.data.get("source"), self.data.get("source_from_scene"))
        self.data["source"], self.data["source_from_scene"] = str(source), beside
        return before != (str(source), beside)

    def save(self) -> None:
        self.data.setdefault("format", MANIFEST_FORMAT)
        write_json_atomic(self.path, self.data)


LOCK_WAIT_S = 1.0
"""How long a run waits for the scene's lock: `recon status` holds it shared for an instant to see whether a run is
going on."""


def _flock_within(fd: int, seconds: float) -> bool:
    """Take the exclusive lock on `fd`, trying again for `seconds`; False if another process holds it all along."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def _lock_holder(fd: int) -> str:
    """The pid the scene's lock file names (its last holder writes it there), "" if it is empty."""
    return os.pread(fd, 64, 0).decode(errors="replace").strip()


@contextlib.contextmanager
def scene_lock(scene_dir: Path) -> Iterator[None]:
    """One `recon` writer per scene folder. flock is released by the kernel when a process dies."""
    lock_path = scene_dir / LOCK
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if not _flock_within(fd, LOCK_WAIT_S):
            holder = _lock_holder(fd) or "another process"
            raise ReconError(
                f"{scene_dir} is in use by another recon process (pid {holder}). Wait for it to finish, "
                f"or stop it, or choose another --out folder."
            )
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)


def running_pid(scene_dir: Path) -> str | None:
    """The pid of the `recon` process writing this scene now (it holds the scene's lock), or None: `recon status`
    shows a run's finished stages while it goes on."""
    try:
        fd = os.open(scene_dir / LOCK, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _lock_holder(fd) or "unknown"
        except OSError:  # a file system without locks (ENOLCK): no run holds one there either
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


LOG_NAMES = frozenset({"logs", "recon-error.log", "batch.log"})
"""recon's own logs in a scene folder (COLMAP's, a crash's, `recon batch`'s), which may precede its manifest."""
RUN_LOG = "logs/run.log"
"""Every line a run showed (stage headers, reasons, warnings, results), appended run after run."""
RECON_NAMES = frozenset({MANIFEST, LOCK, ".work"}) | LOG_NAMES
"""Names recon itself creates directly in a scene folder (besides the stage folders and temporary names)."""


def check_scene_dir(scene_dir: Path, source: Path | None, stage_folders: list[str]) -> None:
    """Refuse an output folder recon could damage: recon writes only into a new or empty folder or a scene it made.

    `scene_dir` must not be the root, the home folder (or above it), must not contain, equal or sit inside the
    photos (`source`), and when it exists and is not empty it must hold a valid recon manifest.json, or recon's
    lock file and nothing but names recon gives its own files (a scene whose manifest was damaged, or a first run
    stopped before its first manifest write).
    """
    resolved = resolve_path(scene_dir, "The output folder")
    why = forbidden_reason(resolved)
    if why:
        raise ReconError(
            f"Refusing to use {scene_dir} as the output folder: it is {why}, and recon would write its scene files "
            f"there. Give --out a new folder, e.g. --out {Path.home() / 'recon-scene'}."
        )
    why = scene_part_reason(resolved, lambda: RECON_NAMES | set(stage_folders))
    if why:
        raise ReconError(f"Refusing to use {scene_dir} as the output folder: it is {why}. Give --out a folder outside it.")
    if source is not None:
        photos = resolve_path(source, "The input")
        relation = overlap_reason(resolved, photos)
        if relation:
            raise ReconError(
                f"The output folder {scene_dir} {relation} {source}. recon must never write among the photos (or the "
                f"photos among its outputs, which it replaces): choose an --out folder outside {photos.parent if photos.is_file() else photos}, "
                f"e.g. --out {photos.parent / (photos.stem + '-scene')}."
            )
    if scene_dir.exists() and not scene_dir.is_dir():
        raise ReconError(f"The output path {scene_dir} is a file, not a folder. Choose a folder path for --out.")
    if not scene_dir.is_dir():
        return
    try:
        entries = {p.name for p in scene_dir.iterdir()}
    except OSError as exc:
        raise ReconError(f"Cannot read the output folder {scene_dir}: {exc.strerror}. Choose another --out.") from None
    if not entries - {LOCK} - LOG_NAMES:
        return  # empty, or only the lock and logs of a run stopped before it wrote anything
    has_manifest = (scene_dir / MANIFEST).is_file()
    if has_manifest and Manifest(scene_dir).warning is None:
        return
    ours = RECON_NAMES | set(stage_folders)
    strays = sorted(n for n in entries if n not in ours and not _is_leftover(n, stage_folders))
    if LOCK in entries and not strays:
        return  # recon's own folder whose manifest was damaged, or not yet written when a run was stopped
    shown = strays or sorted(entries)
    listing = f"{', '.join(shown[:5])}{'…' if len(shown) > 5 else ''}"
    what = (f"{scene_dir / MANIFEST} is not a manifest recon can read" if has_manifest
            else f"{scene_dir} is not empty and is not a recon scene (it has no manifest.json)")
    raise ReconError(
        f"{what}, and the folder holds files recon did not make ({listing}). recon writes only into a new or empty "
        f"folder or a scene it made, so that it never replaces your files: choose another --out folder."
    )


def prepare_scene_dir(scene_dir: Path) -> None:
    """Create the output folder or explain why it cannot be used."""
    if scene_dir.exists() and not scene_dir.is_dir():
        raise ReconError(f"The output path {scene_dir} is a file, not a folder. Choose a folder path for --out.")
    try:
        scene_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReconError(f"Cannot create the output folder {scene_dir}: {exc.strerror}. Choose another --out.") from None
    if not os.access(scene_dir, os.W_OK | os.X_OK):
        raise ReconError(
            f"The output folder {scene_dir} is not writable. Fix its permissions or choose another --out folder."
        )


class Pipeline:
    """Runs an ordered list of stages over one scene folder."""

    def __init__(self, stages: list[Stage]):
        self.stages = stages
        self.by_name = {s.name: s for s in stages}

    def names(self) -> list[str]:
        return [s.name for s in self.stages]

    def select(self, from_stage: str | None, until_stage: str | None) -> list[Stage]:
        names = self.names()
        for given in (from_stage, until_stage):
            if given is not None and given not in names:
                raise ReconError(f"Unknown stage '{given}'. Stages, in order: {', '.join(names)}.")
        start = names.index(from_stage) if from_stage else 0
        stop = names.index(until_stage) if until_stage else len(names) - 1
        if start > stop:
            raise ReconError(f"--from {from_stage} comes after --until {until_stage}; nothing to run.")
        return self.stages[start : stop + 1]

    @staticmethod
    def source_digest(stage: Stage, config: RunConfig, source: Path | None) -> str | None:
        """Digest of the stage's outside input (the photos), or None for stages that read none."""
        if stage.source_digest is None or source is None:
            return None
        return stage.source_digest(source, getattr(config, stage.name, None))

    def fingerprint(
        self, stage: Stage, manifest: Manifest, config: RunConfig, source: Path | None, source_digest: str | None = None,
        without: tuple[str, ...] = (),
    ) -> str:
        """What the stage's output stands for; `without`: config fields left out (the scratch folder's key)."""
        sliced = config_slice(config, stage.name) if hasattr(config, stage.name) else None
        if sliced is not None:
            for key in without:
                sliced.pop(key, None)
        parts: dict[str, Any] = {
            "stage": stage.name,
            "version": stage.version,
            "config": sliced,
            "inputs": {name: manifest.stages.get(name, {}).get("output_digest") for name in stage.inputs},
        }
        if stage.source_digest is not None and source is not None:
            parts["source"] = source_digest or self.source_digest(stage, config, source)
        return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()

    def state(self, scene_dir: Path, config: RunConfig | None = None, source: Path | None = None,
              preset: str | None = None) -> list[dict]:
        """Each stage's state for `recon status`: done / stale / missing / failed / corrupt; a stale row says why
        a run with `config` (the options of `preset`) would make it again."""
        manifest = Manifest(scene_dir)
        rows = []
        photos_changed: set[str] = set()  # stages a run makes from other photos: every stage after them runs again
        remade: dict[str, bool] = {}  # stage a run makes again -> surely (stale, not only maybe): one made from its
        # output runs again if that output differs
        for stage in self.stages:
            entry = manifest.stages.get(stage.name)
            folder = scene_dir / stage.folder
            row = {"stage": stage.name, "folder": stage.folder, "state": "missing", "wall_s": None, "summary": {}}
            if entry:
                row["wall_s"] = entry.get("wall_s")
                row["summary"] = entry.get("summary", {})
                row["finished"] = entry.get("finished")
                if entry.get("last_error"):
                    row["error"] = entry["last_error"]
                if entry.get("status") == "done" and folder.is_dir():
                    row["state"] = "done" if self._outputs_intact(folder, entry) else "corrupt"
                    digest = None
                    photos = source or manifest.source
                    if row["state"] == "done" and config is not None and (photos is None or photos.exists()):
                        digest = self.source_digest(stage, config, photos)
                        if self.fingerprint(stage, manifest, config, photos, digest) != entry.get("fingerprint"):
                            row["state"] = "stale"
                    elif row["state"] == "done" and (changed := self._changed_source(stage, entry, photos)):
                        row["state"], digest = "stale", changed
                    upstream_changed = any(
                        manifest.stages.get(u, {}).get("output_digest") != entry.get("input_digests", {}).get(u)
                        for u in stage.inputs
                    )
                    if row["state"] == "done" and upstream_changed:
                        row["state"] = "stale"
                    recorded = entry.get("source_digest")
                    other_photos = digest is not None and recorded not in (None, _short_digest(digest))
                    after = [u for u in stage.inputs if u in photos_changed]
                    if row["state"] == "stale":
                        row["why"] = rerun_reasons(stage, entry, manifest, config, _short_digest(digest), preset)
                    elif row["state"] == "done" and after:  # its input is made anew from other photos
                        row["state"], row["why"] = "stale", f"after {after[0]}, made from other photos"
                    elif row["state"] == "done" and (again := [u for u in stage.inputs if u in remade]):
                        nearest = max(again, key=lambda u: (remade[u], stage.inputs.index(u)))  # surely, then latest
                        row["why"] = f"if {nearest}'s new output differs from its last"  # only running it tells
                    if other_photos or after:
                        photos_changed.add(stage.name)
                    if row["state"] == "stale" or row.get("why"):
                        remade[stage.name] = row["state"] == "stale"
                elif entry.get("status") == "failed":
                    row["state"] = "failed"
            if scratch := _scratch_note(scene_dir, stage.name):  # e.g. a stopped training, under any options
                row["scratch"] = scratch
            rows.append(row)
        return rows

    @staticmethod
    def _changed_source(stage: Stage, entry: dict, source: Path | None) -> str | None:
        """The digest of the files a finished stage was made from where they changed since, else None (without the
        options, which the fingerprint needs): their names, sizes and times first, their bytes only where those
        differ."""
        if stage.source_digest is None or source is None or entry.get("source_digest") is None:
            return None
        try:
            if stage.source_stat is not None and entry.get("source_stat") == stage.source_stat(source):
                return None
            digest = stage.source_digest(source, None)
        except (OSError, ReconError):  # gone or unreadable: `recon run` says what is wrong with them
            return None
        return digest if _short_digest(digest) != entry["source_digest"] else None

    @staticmethod
    def _outputs_intact(folder: Path, entry: dict) -> bool:
        recorded = entry.get("files")
        if not isinstance(recorded, dict):
            return False
        try:
            return folder_files(folder) == recorded
        except OSError:
            return False

    def run(
        self,
        scene_dir: Path,
        config: RunConfig,
        report: Reporter,
        source: Path | None = None,
        from_stage: str | None = None,
        until_stage: str | None = None,
        force: bool = False,
        preset: str | None = None,
    ) -> list[StageOutcome]:
        """Run the selected stages in order, skipping those whose cache is valid.

        `from_stage` forces that stage to re-run (and what follows re-runs if its output changed);
        `force` re-runs every selected stage; `preset` is recorded so later single-stage runs reuse it.
        """
        folders = [s.folder for s in self.stages]
        check_scene_dir(scene_dir, source, folders)
        prepare_scene_dir(scene_dir)
        with scene_lock(scene_dir):
            check_scene_dir(scene_dir, source, folders)  # again under the lock: nothing changed it meanwhile
            report.log_to(scene_dir / RUN_LOG)
            report.log(f"run: photos {source or 'as recorded'}, preset {preset or 'as recorded'}")
            try:
                outcomes = self._run_locked(scene_dir, config, report, source, from_stage, until_stage, force, preset)
            except BaseException as exc:  # the log says how the run ended, an interrupt or an error included
                report.log(f"stopped: {type(exc).__name__}: {exc}")
                raise
            finally:
                report.log_to(None)
        return outcomes

    def _run_locked(self, scene_dir: Path, config: RunConfig, report: Reporter, source: Path | None,
                    from_stage: str | None, until_stage: str | None, force: bool,
                    preset: str | None) -> list[StageOutcome]:
        """`run`'s stages, under the scene's lock."""
        folders = [s.folder for s in self.stages]
        outcomes: list[StageOutcome] = []
        manifest = Manifest(scene_dir)
        if manifest.warning:
            report.warn(manifest.warning)
        _remove_leftovers(scene_dir, folders)
        recorded = manifest.source
        if source is None and recorded is not None:
            check_scene_dir(scene_dir, recorded, folders)
        source = source or recorded
        selected = self.select(from_stage, until_stage)
        for stage in selected:
            forced = force or stage.name == from_stage
            outcome = self._run_stage(stage, scene_dir, manifest, config, report, source, forced, preset)
            outcomes.append(outcome)
            # recorded only once a stage succeeded: a failed run with other photos or another preset leaves
            # the finished scene's record alone (single-stage commands default to these)
            changed = False
            if stage.needs_source and source is not None:
                before = manifest.data.get("source")
                if outcome.action == "cached" and before is not None and before != str(source):
                    report.info(f"{stage.name}: the same photos, read from {source} now (they were in {before}): "
                                f"what was made from them is kept")
                changed = manifest.record_source(source)
            if preset is not None and outcome.action == "ran" and manifest.data.get("preset") != preset:
                manifest.data["preset"], changed = preset, True
            if changed:
                manifest.save()
        report.log("finished")
        return outcomes

    def _run_stage(
        self,
        stage: Stage,
        scene_dir: Path,
        manifest: Manifest,
        config: RunConfig,
        report: Reporter,
        source: Path | None,
        forced: bool,
        preset: str | None = None,
    ) -> StageOutcome:
        for upstream in stage.inputs:
            entry = manifest.stages.get(upstream, {})
            if entry.get("status") != "done" or not (scene_dir / self.by_name[upstream].folder).is_dir():
                raise ReconError(
                    f"Stage '{stage.name}' needs the output of '{upstream}', which {scene_dir} does not have yet. "
                    f"Run `recon run PHOTOS --out {scene_dir}` (or `recon {upstream} ...`) first."
                )
        if stage.needs_source and source is None:
            raise ReconError(
                f"Stage '{stage.name}' needs the photos folder; give it: `recon run PHOTOS_DIR --out {scene_dir}`."
            )
        if stage.needs_source and source is not None and not source.exists():
            raise ReconError(f"The input {source} does not exist. Check the path (it is recorded in {MANIFEST}); if "
                             f"the photos moved, give `recon run` the folder they are in now: the same photos keep "
                             f"what was made from them.")

        # the files' names, sizes and times before their bytes: one edited while they are read, or while the stage
        # runs, differs from what is kept, and `recon status` then hashes them again
        source_stat = stage.source_stat(source) if stage.source_stat is not None and source is not None else None
        source_digest = self.source_digest(stage, config, source)
        fingerprint = self.fingerprint(stage, manifest, config, source, source_digest)
        entry = manifest.stages.get(stage.name)
        folder = scene_dir / stage.folder
        scratch = self.fingerprint(stage, manifest, config, source, source_digest, without=stage.scratch_survives)
        work = scene_dir / ".work" / f"{stage.name}-{scratch[:16]}"
        if not forced and entry and entry.get("status") == "done" and entry.get("fingerprint") == fingerprint:
            if folder.is_dir() and self._outputs_intact(folder, entry):
                shutil.rmtree(work, ignore_errors=True)  # scratch of a run killed after its manifest entry
                if source_stat is not None and entry.get("source_stat") != source_stat:  # the same bytes, touched or
                    entry["source_stat"] = source_stat  # copied since: kept, so `recon status` need not hash them again
                    manifest.save()
                report.stage_cached(stage.name, entry.get("summary", {}))
                return StageOutcome(stage.name, "cached", 0.0, entry.get("summary", {}))
            report.warn(
                f"Stage '{stage.name}': its files in {folder} no longer match the checksums recorded when they were "
                f"written (changed, truncated or deleted); re-running it."
            )

        previous = why = None
        if entry and entry.get("status") == "done" and entry.get("fingerprint") != fingerprint:  # made otherwise
            why = rerun_reasons(stage, entry, manifest, config, _short_digest(source_digest), preset, source)
            if entry.get("scratch") == scratch and folder.is_dir() and self._outputs_intact(folder, entry):
                previous = folder
        tmp = scene_dir / f".tmp-{stage.folder}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        work.mkdir(parents=True, exist_ok=True)
        ctx = StageContext(
            name=stage.name,
            folder=stage.folder,
            out=tmp,
            work=work,
            inputs={u: scene_dir / self.by_name[u].folder for u in stage.inputs},
            config=getattr(config, stage.name, None),
            run_config=config,
            source=source,
            scene_dir=scene_dir,
            report=report,
            previous=previous,
        )
        started, t0 = _now(), time.perf_counter()
        report.stage_start(stage.name)
        if why is not None:  # the stage says how it goes on from `previous`; made anew, say what would have kept it
            anew = (f"; made anew (only a change of {', '.join(f'{stage.name}.{k}' for k in stage.scratch_survives)} "
                    "carries its output on)" if stage.scratch_survives and previous is None else "")
            report.info(f"{stage.name} runs again: {why}{anew}")
        try:
            fault_point(f"{stage.name}/start")
            summary = stage.run(ctx) or {}
            files = folder_files(tmp)
            fault_point(f"{stage.name}/after-output")
        except BaseException as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            if not isinstance(exc, (KeyboardInterrupt, SystemExit)):
                record = manifest.stages.setdefault(stage.name, {})
                record["last_error"] = _error_line(exc)
                record["last_attempt"] = _now()
                if record.get("status") != "done":
                    record["status"] = "failed"
                manifest.save()
            raise
        wall = time.perf_counter() - t0
        _swap_into_place(tmp, folder, stage.name)
        fault_point(f"{stage.name}/after-swap")
        input_digests = {u: manifest.stages[u]["output_digest"] for u in stage.inputs}
        manifest.stages[stage.name] = {
            "status": "done",
            "fingerprint": fingerprint,
            "scratch": scratch,  # the fingerprint less scratch_survives: which later runs get this output as previous
            "version": stage.version,  # with source_digest and config: what a later run says changed (rerun_reasons)
            "source_digest": _short_digest(source_digest),
            "source_stat": source_stat,
            "preset": preset,  # the preset whose options `config` holds, so a later run can name the one it changed
            "input_digests": input_digests,
            # what this output means, not only its bytes: it also stands for the upstream outputs and the photos it
            # refers to by path, so a changed photo re-runs every later stage even when a scene.json comes out equal
            "output_digest": digest_of({"files": files, "inputs": input_digests, "source": source_digest}),
            "files": files,
            "started": started,
            "finished": _now(),
            "wall_s": round(wall, 3),
            "config": config_slice(config, stage.name) if hasattr(config, stage.name) else None,
            "versions": package_versions(),
            "summary": summary,
        }
        manifest.save()
        fault_point(f"{stage.name}/after-manifest")
        shutil.rmtree(work, ignore_errors=True)
        report.stage_done(stage.name, wall, summary)
        return StageOutcome(stage.name, "ran", wall, summary)


def _short_digest(source_digest: str | None) -> str | None:
    return hashlib.sha256(source_digest.encode()).hexdigest() if source_digest is not None else None


def _shown(value: Any, width: int = 40) -> str:
    text = json.dumps(value, default=str) if not isinstance(value, str) else value or '""'
    return text if len(text) <= width else text[:width - 1] + "…"


def _changed_options(prefix: str, old: dict, new: dict) -> list[str]:
    """`prefix.key old → new` for each option that differs, nested sections key by key."""
    changed = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            changed += _changed_options(f"{prefix}.{key}", a, b)
        elif key not in old:  # made by a recon without the option: say so rather than "None → value"
            changed.append(f"{prefix}.{key} {_shown(b)} (an option new in this recon)")
        elif key not in new:
            changed.append(f"{prefix}.{key} (no longer an option)")
        elif a != b:
            changed.append(f"{prefix}.{key} {_shown(a)} → {_shown(b)}")
    return changed


def rerun_reasons(stage: Stage, entry: dict, manifest: Manifest, config: RunConfig | None, source_digest: str | None,
                  preset: str | None = None, source: Path | None = None, most: int = 4) -> str:
    """Why a finished stage runs again, as its entry in the manifest tells against this run: another preset (`preset
    fast → quality`) and the options that changed (`train.lr 0.01 → 0.003`), an upstream output that changed, other
    photos (saying so when they are read from another folder too), or another recipe of the stage. Without a
    config (`recon status` given no options) only what the manifest itself tells."""
    reasons = []
    if config is not None and preset is not None and entry.get("preset") not in (None, preset):
        reasons.append(f"preset {entry['preset']} → {preset}")
    if entry.get("version") not in (None, stage.version):
        reasons.append(f"this recon makes it differently (stage version {entry['version']} → {stage.version})")
    if (entry.get("source_digest") is not None and source_digest not in (None, entry["source_digest"])
            and entry.get("version") in (None, stage.version)):  # another recipe may read the same photos otherwise
        before = manifest.data.get("source")
        moved = source is not None and before is not None and Path(before) != source
        reasons.append(f"the photos changed (read from {source} now, not {before})" if moved else "the photos changed")
    for name in stage.inputs:
        if entry.get("input_digests", {}).get(name) != manifest.stages.get(name, {}).get("output_digest"):
            reasons.append(f"the {name} stage's output changed")
    old = entry.get("config")
    new = config_slice(config, stage.name) if config is not None and hasattr(config, stage.name) else None
    if isinstance(old, dict) and isinstance(new, dict):
        kept = json.loads(json.dumps(new, default=str))  # as the manifest keeps it (tuples as lists)
        changed = _changed_options(stage.name, old, kept)
        more = len(changed) - most
        reasons += changed[:most] + ([f"{more} more option{'s' if more > 1 else ''}"] if more > 0 else [])
    if reasons:
        return ", ".join(reasons)
    return ("the photos or this recon's recipe for it changed" if stage.source_digest is not None else  # an older
            "this recon's recipe for it changed")  # manifest, without the version and source digest its entries keep


def _scratch_note(scene_dir: Path, stage: str) -> str | None:
    """What the newest of the stage's scratch folders holds, as its note says, with where and how large it is."""
    notes = sorted(scene_dir.joinpath(".work").glob(f"{stage}-*/{SCRATCH_NOTE}"), key=lambda p: p.stat().st_mtime)
    if not notes:
        return None
    try:
        headline = str(read_json(notes[-1])["headline"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    size = sum(p.stat().st_size for p in notes[-1].parent.rglob("*") if p.is_file())
    return f"{headline} ({size / 2**20:.0f} MB in {notes[-1].parent.relative_to(scene_dir)})"


def _error_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:300]


def recorded_source(scene_dir: Path) -> Path | None:
    """The input the scene was last run on (its manifest's `source`): where commands that read the scene's photos
    after a run (export, eval, the viewer) find them. None for a scene without a readable manifest."""
    try:
        return Manifest(Path(scene_dir)).source
    except (OSError, ValueError, ReconError):
        return None


def _swap_into_place(tmp: Path, folder: Path, stage: str = "") -> None:
    """Replace `folder` by `tmp` so that a crash at any point leaves one complete folder or a leftover to clean.

    Old folder → `.old-NAME` (rename), tmp → folder (rename), then delete the old one. A crash between
    the two renames leaves no `folder`: the manifest's checksums then fail and the stage re-runs.
    """
    old = folder.with_name(f".old-{folder.name}-{os.getpid()}")
    if folder.exists():
        os.rename(folder, old)
        fault_point(f"{stage}/mid-swap")
    os.rename(tmp, folder)
    _fsync_dir(folder.parent)
    if old.exists():
        shutil.rmtree(old, ignore_errors=True)


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _is_leftover(name: str, stage_folders: list[str]) -> bool:
    """A temporary name recon makes in a scene folder: `.tmp-FOLDER-PID`, `.old-FOLDER-PID` or `.manifest.json.PID.tmp`."""
    for prefix in (".tmp-", ".old-"):
        folder, sep, pid = name.removeprefix(prefix).rpartition("-")
        if name.startswith(prefix) and sep and pid.isdigit() and folder in stage_folders:
            return True
    return is_temp_name(name) and name.startswith(f".{MANIFEST}.")


def _remove_leftovers(scene_dir: Path, stage_folders: list[str]) -> None:
    """Temporary and superseded folders of interrupted runs (we hold the lock, so none is in use).

    Only names recon makes, and only in a scene recon owns (`check_scene_dir` ran first); links are unlinked,
    never followed."""
    for path in scene_dir.iterdir():
        if not _is_leftover(path.name, stage_folders):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def install_sigterm_as_interrupt() -> None:
    """Treat SIGTERM like Ctrl-C so a stopped run cleans its temporary folder and checkpoints."""
    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    with contextlib.suppress(ValueError):
        signal.signal(signal.SIGTERM, handler)


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)
