"""Progress display: stage headers, bars with ETA, warnings, and the closing summary (rich).

Stages never print directly; they call a Reporter so that the CLI, tests (quiet) and benchmarks can
choose how much is shown.
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from datetime import datetime
from pathlib import Path
from typing import IO, Any

from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Column
from rich.text import Text


class Task:
    """A handle on one progress bar: advance it, change its total, or show a short status text."""

    def __init__(self, progress: Progress | None, task_id: TaskID | None):
        self._progress, self._id = progress, task_id

    def advance(self, n: float = 1) -> None:
        if self._progress is not None and self._id is not None:
            self._progress.advance(self._id, n)

    def update(self, completed: float | None = None, total: float | None = None, info: str | None = None) -> None:
        if self._progress is None or self._id is None:
            return
        kwargs: dict[str, Any] = {}
        if completed is not None:
            kwargs["completed"] = completed
        if total is not None:
            kwargs["total"] = total
        if info is not None:
            kwargs["info"] = info
        self._progress.update(self._id, **kwargs)


class Reporter:
    """Console output for a run. `quiet=True` keeps warnings and errors only (used by tests)."""

    def __init__(self, console: Console | None = None, quiet: bool = False):
        self.console = console or Console(stderr=True, highlight=False)
        self.quiet = quiet
        self.current_stage: str | None = None
        self.warnings: list[str] = []
        self.observers: list[Callable[[str, dict], None]] = []
        """Live observers (the viewer): `observe(event, data)` calls each, on the stage's thread."""
        self._log: IO[str] | None = None

    def log_to(self, path: Path | None) -> None:
        """Also append every line this reporter shows (not its bars), quiet or not, to `path`: a run's reasons and
        results outlive the terminal. None closes the log."""
        if self._log is not None:
            self._log.close()
            self._log = None
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                self._log = open(path, "a", encoding="utf-8", buffering=1)  # a line at a time: an interrupt keeps it
            except OSError as exc:  # the log is a record beside the run, not a reason to stop it
                self.warn(f"the run's log {path} cannot be written ({exc.strerror or exc}); the run goes on without it")

    def log(self, text: str) -> None:
        """A plain line for the log only (nothing when no log is open)."""
        if self._log is not None:
            stamp = time.strftime("%Y-%m-%d %H:%M:%S")
            self._log.writelines(f"{stamp}  {line}\n" for line in text.splitlines() or [""])

    def stage_start(self, name: str) -> None:
        self.current_stage = name
        self.log(f"== {name} ==")
        if not self.quiet:
            self.console.rule(f"[bold]{name}")

    def stage_cached(self, name: str, summary: dict) -> None:
        self.log(f"{name}: up to date (cached) — {format_summary(summary)}")
        if not self.quiet:
            self.console.print(f"[green]✓[/] {name}: up to date (cached) — {escape(format_summary(summary))}")

    def stage_done(self, name: str, wall_s: float, summary: dict) -> None:
        self.log(f"{name} done in {format_seconds(wall_s)} — {format_summary(summary)}")
        if not self.quiet:
            self.console.print(f"[green]✓[/] {name} done in {format_seconds(wall_s)} — {escape(format_summary(summary))}")

    def info(self, message: str, markup: bool = False) -> None:
        """Print a line; plain text unless `markup` (paths may hold '[' and ']', which must print as they are)."""
        self.log(Text.from_markup(message).plain if markup else message)
        if not self.quiet:
            self.console.print(message, markup=markup)

    def observe(self, event: str, data: dict) -> None:
        for fn in self.observers:
            fn(event, data)

    def warn(self, message: str) -> None:
        self.warnings.append(message)
        self.log(f"warning: {message}")
        self.console.print(f"[yellow]warning:[/] {escape(message)}")

    @contextlib.contextmanager
    def task(self, description: str, total: float | None = None, unit: str = "") -> Iterator[Task]:
        """A bar with elapsed time and ETA (a spinner when the total is unknown)."""
        if self.quiet:
            yield Task(None, None)
            return
        stage = f"[cyan]{self.current_stage}[/] " if self.current_stage else ""
        # in a narrow terminal a shorter bar, and the description wraps: rich would otherwise shrink the count, the
        # elapsed time and the ETA to '…' (80 columns) to keep each on one line
        columns = [
            SpinnerColumn(),
            TextColumn(f"{stage}{escape(description)}", table_column=Column(no_wrap=False)),
            BarColumn(bar_width=40 if self.console.width >= 120 else 16),
            MofNCompleteColumn(),
            TextColumn(escape(unit)),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            TextColumn("{task.fields[info]}", table_column=Column(no_wrap=False, overflow="fold")),
        ]
        with Progress(*columns, console=self.console, transient=False) as progress:
            task_id = progress.add_task(description, total=total, info="")
            yield Task(progress, task_id)


def local_minute(stamp: str | None) -> str:
    """A manifest's UTC time stamp as the reader's local date and minute (YYYY-MM-DD HH:MM); "" for none, the stamp
    itself if it does not parse."""
    if not stamp:
        return ""
    try:
        return datetime.fromisoformat(stamp).astimezone().strftime("%Y-%m-%d %H:%M")
    except (TypeError, ValueError):
        return str(stamp)


def format_seconds(seconds: float | None) -> str:
    if seconds is None:
        return "—"
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, sec = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {sec:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def format_summary(summary: dict) -> str:
    """The stage's own one-line summary: its `headline` if it gave one, else key=value pairs."""
    if not summary:
        return ""
    if "headline" in summary:
        return str(summary["headline"])
    return ", ".join(f"{k}={v}" for k, v in summary.items() if not isinstance(v, (dict, list)))
