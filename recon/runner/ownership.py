"""Which folders recon may write into and which files in them it may replace: the one home of that rule.

recon writes into a folder only when it is new or empty, or carries recon's own record for that kind of output
(a scene's manifest.json for `recon run`, checked by the runner; `.recon-KIND.json` for a batch, an export, a
render, a benchmark, an evaluation or an image fit), and never into the root, the home folder, the photos or a stage folder of a scene. The record lists every
file recon put there, so a later run replaces only those: a file the user added is kept, and one that stands where
recon would write is refused before anything is written, never overwritten.
"""
from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from recon.atomic import read_json, write_json_atomic
from recon.errors import InputError

STAGING_PREFIX = ".recon-staging-"
"""Where an output is built before its files move into place: `OUT/.recon-staging-PID/`."""
KIND_WORDS = {"batch": "a recon batch", "export": "a recon export", "render": "a recon render",
              "bench": "a recon benchmark", "fit-image": "a recon image fit", "eval": "a recon evaluation"}
KIND_VERBS = {"batch": "write", "export": "export", "render": "render", "bench": "write", "fit-image": "write",
              "eval": "write"}


def marker_name(kind: str) -> str:
    """The record recon keeps in a folder it wrote one kind of output into: `.recon-export.json`, say."""
    return f".recon-{kind}.json"


def resolve_path(path: Path, what: str) -> Path:
    """`path` made absolute with every link followed, or an InputError naming the link that loops or leads nowhere.

    `what` starts the message ("--out", "The capture"). A path that does not exist yet is fine; one whose nearest
    existing part is a link to nothing (or a loop) is not: recon cannot tell where the user meant to write.
    """
    try:
        resolved = path.resolve()
    except (RuntimeError, OSError):  # a link loop: RuntimeError up to Python 3.12, OSError (ELOOP) from 3.13
        resolved = None
    probe = Path(os.path.abspath(path))
    while not os.path.lexists(probe) and probe != probe.parent:
        probe = probe.parent
    if resolved is None or (probe.is_symlink() and not probe.exists()):
        link = probe if probe.is_symlink() else path
        target = os.readlink(link) if link.is_symlink() else "itself"
        raise InputError(
            f"{what} {path} goes through the symbolic link {link} → {target}, which loops or points to nothing. "
            f"Fix or remove the link, or give a real folder."
        )
    return resolved


def forbidden_reason(resolved: Path) -> str | None:
    """Why a resolved path can never hold recon's output: the root, the home folder or a folder above it."""
    home = Path.home().resolve()
    if resolved == Path(resolved.anchor):
        return "the root of the file system"
    if resolved == home:
        return "your home folder"
    if resolved in home.parents:
        return "a folder that holds your home folder"
    return None


def overlap_reason(resolved: Path, source: Path) -> str | None:
    """How an output folder overlaps an input (both resolved): 'is', 'contains' or 'is inside' the input, else None."""
    if source == resolved:
        return "is the input"
    if resolved in source.parents:
        return "contains the input"
    if source in resolved.parents:
        return "is inside the input"
    return None


def scene_part_reason(resolved: Path, scene_parts: Callable[[], Collection[str]]) -> str | None:
    """Why `resolved` lies inside a part of a scene recon manages (a stage folder, its logs, its scratch), else None.

    A scene is a folder with a manifest.json above `resolved`; `scene_parts()` names what recon makes at its top
    level (`recon.stages.scene_parts`: called only when a scene is found, so a plain --out never loads the stages).
    The scene folder itself is not refused here: it is a non-empty folder with recon's record of a run, which only
    `recon run` may write into.
    """
    for scene in resolved.parents:
        if not (scene / "manifest.json").is_file():
            continue
        top = resolved.relative_to(scene).parts[0]
        if top not in scene_parts():
            return None
        return f"inside {scene / top}, a part of the scene {scene} that recon replaces or cleans up when it runs"
    return None


def _problem(resolved: Path, inputs: Sequence[Path], scene_parts: Callable[[], Collection[str]]) -> str | None:
    why = forbidden_reason(resolved)
    if why:
        return f"it is {why}"
    for source in inputs:
        relation = overlap_reason(resolved, source)
        if relation:
            return f"it {relation} {source}, and recon never writes among its inputs (nor puts them among its outputs)"
    why = scene_part_reason(resolved, scene_parts)
    if why:
        return f"it is {why}"
    return None


@dataclass
class OwnedFolder:
    """A folder recon may write one kind of output into, with the files its record says recon put there."""

    path: Path
    kind: str
    files: set[str] = field(default_factory=set)
    """Paths relative to `path` (POSIX) that recon wrote there: the only ones it may replace or remove."""
    record: dict[str, Any] = field(default_factory=dict)
    """Whatever else the output keeps in its record (a batch: which capture each folder holds)."""
    created: bool = False

    @property
    def marker(self) -> Path:
        return self.path / marker_name(self.kind)

    def save(self, files: Iterable[str] | None = None) -> None:
        """Create the folder if needed and write its record (atomically), listing `files` (default: the current set)."""
        if files is not None:
            self.files = set(files)
        if not self.path.is_dir():
            try:
                self.path.mkdir(parents=True)
            except OSError as exc:
                raise InputError(f"Cannot create the folder {self.path}: {exc.strerror}. Choose another --out.") from None
            self.created = True
        write_json_atomic(self.marker, {**self.record, "kind": self.kind, "files": sorted(self.files)})

    def check_free(self, names: Iterable[str]) -> None:
        """Refuse (InputError, nothing written) when any of `names` would replace something recon did not put there,
        or would be written through a link inside the folder."""
        blocked = []
        for name in names:
            target = self.path / name
            parent = self.path
            for part in Path(name).parts[:-1]:
                parent = parent / part
                if parent.is_symlink() or (parent.exists() and not parent.is_dir()):
                    blocked.append(parent.relative_to(self.path).as_posix())
                    break
            else:
                if os.path.lexists(target) and (name not in self.files or target.is_dir()):
                    blocked.append(name)
        if blocked:
            shown = ", ".join(sorted(set(blocked))[:5]) + ("…" if len(set(blocked)) > 5 else "")
            raise InputError(
                f"{self.path} holds {shown}, which recon did not write there (not in its {marker_name(self.kind)}), and "
                f"recon does not replace what it did not make. Move them away, or choose another --out folder."
            )

    @contextlib.contextmanager
    def staging(self) -> Any:
        """A fresh folder inside this one to build the output in; removed (and this folder too, if it was new and
        stays empty) when the block fails."""
        if not self.marker.is_file():
            self.save()  # the folder carries its record before anything of the output is in it
        staged = self.path / f"{STAGING_PREFIX}{os.getpid()}"
        shutil.rmtree(staged, ignore_errors=True)
        staged.mkdir()
        try:
            yield staged
        except BaseException:
            shutil.rmtree(staged, ignore_errors=True)
            if self.created and not self.files:
                shutil.rmtree(self.path, ignore_errors=True)
            raise

    def replace_with(self, staged: Path) -> list[Path]:
        """Move every file built in `staged` into place (each one atomically), remove the files of recon's earlier
        output that this one no longer has, record the new list and delete `staged`. Returns the files placed."""
        new = sorted(p.relative_to(staged).as_posix() for p in staged.rglob("*") if p.is_file() and not p.is_symlink())
        self.check_free(new)
        self.save(self.files | set(new))  # a crash while files move leaves every one of them recorded as recon's
        for name in new:
            (self.path / name).parent.mkdir(parents=True, exist_ok=True)
            os.replace(staged / name, self.path / name)
        for name in sorted(self.files - set(new)):
            _remove_ours(self.path, name)
        self.save(new)
        shutil.rmtree(staged, ignore_errors=True)
        return [self.path / name for name in new]


def _remove_ours(folder: Path, name: str) -> None:
    """Remove a file recon recorded, then the folders it leaves empty (never one that still holds anything)."""
    path = folder / name
    if path.is_symlink() or path.is_file():
        path.unlink()
    parent = path.parent
    while parent != folder and parent.is_dir() and not parent.is_symlink() and not any(parent.iterdir()):
        parent.rmdir()
        parent = parent.parent


def _read_record(marker: Path, folder: Path) -> tuple[set[str], dict[str, Any]]:
    try:
        data = read_json(marker)
    except (OSError, ValueError) as exc:
        raise InputError(
            f"{marker} is damaged ({exc}), so recon cannot tell which files in {folder} it made. Move the files you want "
            f"to keep out of {folder} and delete it, or choose another --out folder."
        ) from None
    if not isinstance(data, dict):
        data = {}
    files = data.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        # a record from before recon listed its files: that recon replaced the whole folder, so everything was its own
        files = [p.relative_to(folder).as_posix() for p in folder.rglob("*")
                 if p.is_file() and p != marker and not p.name.startswith(STAGING_PREFIX)]
        data = {k: v for k, v in data.items() if k != "files"}
    record = {k: v for k, v in data.items() if k not in ("kind", "files")}
    return set(files), record


def claim_folder(out: Path, kind: str, scene_parts: Callable[[], Collection[str]], inputs: Sequence[Path] = (),
                 option: str = "--out") -> OwnedFolder:
    """Check that recon may write `kind` output into `out`, and read what it wrote there before; writes nothing.

    Refused (InputError): a link that loops or leads nowhere, the root, the home folder or above, a folder that
    is, holds or sits inside one of `inputs`, a part of a scene recon manages, a file, and a non-empty folder
    without this kind's record (a batch, export or render folder of another kind included).
    """
    resolved = resolve_path(out, option)
    what = KIND_WORDS.get(kind, f"recon's {kind}")
    sources = [resolve_path(Path(p), "The input") for p in inputs]
    why = _problem(resolved, sources, scene_parts)
    if why:
        raise InputError(f"Refusing to write {what} into {out}: {why}. Give {option} a new folder elsewhere.")
    if os.path.lexists(resolved) and not resolved.is_dir():
        raise InputError(f"{option} {out} is a file, not a folder. Give {option} a folder path.")
    if not resolved.is_dir():
        return OwnedFolder(resolved, kind)
    marker = resolved / marker_name(kind)
    if marker.is_file():
        files, record = _read_record(marker, resolved)
        for leftover in resolved.glob(f"{STAGING_PREFIX}*"):  # a run stopped while it built its output
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover, ignore_errors=True)
        return OwnedFolder(resolved, kind, files, record)
    try:
        entries = sorted(p.name for p in resolved.iterdir())
    except OSError as exc:
        raise InputError(f"Cannot read the folder {out}: {exc.strerror}. Choose another {option}.") from None
    if not entries:
        return OwnedFolder(resolved, kind)
    others = [k for k in KIND_WORDS if (resolved / marker_name(k)).is_file()] + (["run"] if "manifest.json" in entries else [])
    holds = (f"it holds {KIND_WORDS.get(others[0], 'a recon scene')}, not {what}" if others
             else f"it holds files that recon did not {KIND_VERBS.get(kind, 'make')} ({', '.join(entries[:5])}{'…' if len(entries) > 5 else ''})")
    raise InputError(
        f"Refusing to write {what} into {out}: {holds}. recon writes only into a new or empty folder or one it made "
        f"for the same kind of output, so that it never replaces your files: give {option} another folder."
    )


def claim_names(out: Path, kind: str, scene_parts: Callable[[], Collection[str]], names: Iterable[str],
                unrecorded: Callable[[Path], Collection[str] | None] = lambda folder: None) -> OwnedFolder:
    """`claim_folder` for an output written file by file into `out` (not built in a staging folder): each of `names`
    is refused where a file recon did not write stands, then recorded as recon's before it is written (a crash leaves
    it recon's). `unrecorded(out)`, for a folder without this kind's record: the files it holds when all of them are
    this kind's output (as recon left such folders before it kept a record), else None (the folder stays refused)."""
    earlier = OwnedFolder(out, kind)
    if out.is_dir() and not out.is_symlink() and not earlier.marker.exists():
        files = unrecorded(out)
        if files is not None:
            earlier.save(files)
    owned = claim_folder(out, kind, scene_parts)
    names = list(names)
    owned.check_free(names)
    owned.save(owned.files | set(names))
    return owned

