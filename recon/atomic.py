"""Atomic file writes, sha256 sidecars and deferred interrupts: the one home of recon's careful I/O.

Every file recon writes appears whole or not at all: it is written as `.NAME.PID.tmp` next to its final
place (created exclusively, never through a link planted there), fsynced, then renamed over the target.
The runner, the scene, the field, the mesh export and the plots all write through here.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

_FAULT_HITS: dict[str, int] = {}


def fault_point(point: str) -> None:
    """Fault injection for the reliability tests; a no-op unless RECON_FAULT is set.

    RECON_FAULT="POINT[*N][:ACTION]" acts at the N-th (default first) pass through the named point.
    Points: "STAGE/start", "STAGE/after-output", "STAGE/mid-swap", "STAGE/after-swap",
    "STAGE/after-manifest", "train/checkpoint" (after each checkpoint is complete), and "write/FILENAME"
    (inside `atomic_open`, before its rename).
    ACTION: "kill" (default: SIGKILL now), "kill-after-S" (SIGKILL S seconds later, wherever the process
    then is), "enospc" (raise OSError(ENOSPC) as a full disk would).
    """
    spec = os.environ.get("RECON_FAULT")
    if not spec:
        return
    target, _, action = spec.partition(":")
    name, _, nth = target.partition("*")
    if name != point:
        return
    _FAULT_HITS[point] = _FAULT_HITS.get(point, 0) + 1
    if _FAULT_HITS[point] != int(nth or 1):
        return
    if action == "enospc":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), point)
    if action.startswith("kill-after-"):
        timer = threading.Timer(float(action.removeprefix("kill-after-")), os.kill, (os.getpid(), signal.SIGKILL))
        timer.daemon = True
        timer.start()
        return
    os.kill(os.getpid(), signal.SIGKILL)


def temp_path(path: Path) -> Path:
    """The temporary name a write to `path` goes through (the runner removes such leftovers of crashed runs)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def is_temp_name(name: str) -> bool:
    """Whether a file name is one `temp_path` makes: `.NAME.PID.tmp`."""
    if not (name.startswith(".") and name.endswith(".tmp")):
        return False
    stem, _, pid = name[1:-4].rpartition(".")
    return bool(stem) and pid.isdigit()


def sha256_file(path: Path, block: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in blocks."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:  # not the module's `open`: tests replace that one to fake a full disk on writes
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


@contextlib.contextmanager
def atomic_open(path: Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a fresh temporary file next to `path`; when the block ends cleanly, fsync it and rename it over
    `path` (readers see the old or the new file, never half). On any error the temporary file is removed,
    so a full disk does not also leave half a file behind. `mode` is "wb" or "w"."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes whole files: mode 'w' or 'wb', got {mode!r}")
    tmp = temp_path(path)
    tmp.unlink(missing_ok=True)  # ours from a killed run with this pid; "x" below then never follows a link
    try:
        with open(tmp, mode.replace("w", "x")) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        fault_point(f"write/{path.name}")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: Path, data: bytes | str) -> Path:
    """Write bytes (or UTF-8 text) to `path` atomically; returns `path`."""
    with atomic_open(path, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    return path


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON (indented, newline-terminated) to `path` atomically."""
    with atomic_open(path, "w") as f:
        json.dump(data, f, indent=2, sort_keys=False)
        f.write("\n")


def checksum_path(path: Path) -> Path:
    """The sha256 sidecar of `path`: `NAME.sha256`, JSON {"sha256", "size"}."""
    return path.with_name(path.name + ".sha256")


def write_checksummed(path: Path, write: Callable[[IO[bytes]], None]) -> None:
    """Atomically write `path` with `write(file)`, then its sha256 sidecar, with Ctrl-C held until both are
    whole (see `interrupts_deferred`). `checksum_matches` tells later whether the file is still intact."""
    with interrupts_deferred():
        with atomic_open(path, "wb") as f:
            write(f)
        write_json_atomic(checksum_path(path), {"sha256": sha256_file(path), "size": path.stat().st_size})


def checksum_matches(path: Path) -> bool:
    """Whether `path` exists and its bytes match the sidecar `write_checksummed` recorded."""
    try:
        recorded = json.loads(checksum_path(path).read_text())["sha256"]
        return sha256_file(path) == recorded
    except (OSError, ValueError, KeyError, TypeError):
        return False


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C/SIGTERM until the block ends, then raise KeyboardInterrupt.

    torch.save turns an exception raised inside its writer into a RuntimeError ("unexpected pos"), so a
    signal landing mid-save would read as a crash instead of a clean stop. Outside the main thread
    (where handlers cannot be set) the block just runs.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if pending:
        raise KeyboardInterrupt


def read_json(path: Path) -> Any:
    """Parse a JSON file, or raise ValueError saying why not in one line: not UTF-8, invalid, nested too
    deeply, or a number too long for Python. A UTF-8 byte-order mark (Windows editors write one) is accepted."""
    try:
        return json.loads(path.read_bytes().decode("utf-8-sig"))
    except UnicodeDecodeError:
        raise ValueError("it is not UTF-8 text") from None
    except RecursionError:
        raise ValueError("it is nested too deeply to be a recon or poses file") from None
    except ValueError as exc:  # JSONDecodeError, and int() refusing a number of more than 4300 digits
        if "digits" in str(exc) and "limit" in str(exc):
            raise ValueError("a number in it has more than 4300 digits") from None
        raise ValueError(f"it is not valid JSON ({str(exc).splitlines()[0][:200]})") from None
