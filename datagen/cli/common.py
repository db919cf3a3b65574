"""What every command shares: the consoles, the one user-error handler, shared option types.

Command modules import this module and nothing else from `datagen.cli`; `datagen.cli.main` (and
`datagen.cli.shards` for its group) register their plain functions.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    Task,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text
from typer.core import TyperCommand

from schemas.errors import DatagenError

console = Console()
error_console = Console(stderr=True)

EXIT_USER_ERROR = 2
"""Exit code of a command stopped by a user error (`DatagenError`); 1 means "ran, found problems"."""

ConfigOption = Annotated[
    Path | None, typer.Option("--config", "-c", help="Generation config (TOML); defaults otherwise.")
]
UrlArgument = Annotated[str, typer.Argument(metavar="URL", help="Dataset: a local path or an fsspec URL.")]


@contextmanager
def user_errors(url: str | None = None) -> Iterator[None]:
    """Print a user-caused error (any `DatagenError`: datagen's own, `storage.StorageError`,
    `jobs.LedgerError`) as one ``error: <message>`` line on stderr and exit with `EXIT_USER_ERROR`;
    bugs keep their traceback. With the command's dataset ``url``, a failure of its store met
    mid-command (the store went away after `storage.check_store` passed) is such a line too; a pipe
    closed by its reader never is (click ends the command quietly, as ``head`` expects)."""
    try:
        yield
    except DatagenError as exc:
        _print_error(str(exc))
    except BrokenPipeError:
        raise  # the reader of our output closed it (`| head`): click ends the command quietly, no one's fault
    except Exception as exc:
        from storage import is_store_failure, storage_failure

        if url is None or not is_store_failure(exc):
            raise
        _print_error(str(storage_failure(url, exc)))


def _print_error(message: str) -> None:
    error_console.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(EXIT_USER_ERROR)


def lazy_help(**fillers: Callable[[], str]) -> type[TyperCommand]:
    """A command class whose options' help is written when help is shown (``fillers``: option name ->
    its help), from registries that import what a command runs (planners, refiners, export layouts):
    only ``--help`` pays for them, never every command's start."""

    class LazyHelpCommand(TyperCommand):
        def format_help(self, ctx: Any, formatter: Any) -> None:
            for param in self.params:
                if param.name in fillers:
                    param.help = fillers[param.name]()  # type: ignore[attr-defined]
            super().format_help(ctx, formatter)

    return LazyHelpCommand


def dataset_options(url: str) -> dict[str, Any]:
    """fsspec options of a dataset URL: the bounded timeouts and retries of `RunSettings`."""
    from datagen.settings import RunSettings

    return RunSettings().storage_options(url)


def plural(count: int, noun: str) -> str:
    """``1 task``, ``2 tasks``: a count and its noun, as people write them."""
    return f"{count} {noun}{'' if count == 1 else 's'}"


def say(text: str) -> None:
    """One line on stdout exactly as given: no markup, no highlighting, no wrapping."""
    console.print(text, markup=False, highlight=False, soft_wrap=True)


Cell = str | Text


def print_rows(
    columns: list[str], rows: Iterable[list[Cell]], out: Console | None = None, whole: Iterable[str] = ()
) -> None:
    """A rich table on a terminal (``str`` cells are plain text, not markup); elsewhere (a pipe, a file,
    a test runner) a tab-separated header and one tab-separated line per row, never wrapped, so a long
    message stays on its line for grep and cut. Rows are written as they come there (a listing of
    100,000 rows is never held).

    On a terminal no cell is cut short with an ellipsis: a cell too wide for its column is folded
    onto more lines, and the ``whole`` columns (the ids the next command takes: a job, a task) keep
    every value on one line, at the other columns' expense, however narrow the terminal."""
    out = out or console
    if out.is_terminal:
        held = [[Text(cell) if isinstance(cell, str) else cell for cell in row] for row in rows]
        keep = set(whole)
        table = Table()
        for number, name in enumerate(columns):
            if name in keep:
                widest = max([len(name), *(row[number].cell_len for row in held)])
                table.add_column(name, no_wrap=True, min_width=widest)
            else:
                table.add_column(name, overflow="fold")
        for row in held:
            table.add_row(*row)
        out.print(table)
        return
    # Written past rich, which would expand the tabs to spaces.
    header: list[Cell] = list(columns)
    for cells in itertools.chain([header], rows):
        plain = (cell.plain if isinstance(cell, Text) else cell for cell in cells)
        out.file.write("\t".join(" ".join(text.split("\t")) for text in plain) + "\n")
    out.file.flush()


def print_table(table: Table, out: Console | None = None) -> None:
    """A rich table as it is on a terminal; elsewhere its title (if any) on a line of its own, then its
    header (if shown) and rows as tab-separated lines, never wrapped or cut (ids, names and hashes are
    copied from them whole)."""
    out = out or console
    if out.is_terminal:
        out.print(table)
        return
    lines: list[list[str]] = []
    if table.title:
        lines.append([str(table.title)])
    columns = table.columns
    if table.show_header:
        lines.append([str(column.header) for column in columns])
    for row in range(table.row_count):
        lines.append([_plain(column._cells[row]) for column in columns])
    for cells in lines:
        out.file.write("\t".join(" ".join(cell.split("\t")) for cell in cells) + "\n")
    out.file.flush()


def _plain(cell: object) -> str:
    return cell.plain if isinstance(cell, Text) else str(cell)


def progress_bar(remaining: bool = False) -> Progress:
    """A transient bar for a long command (``remaining``: with the time left); off a terminal (a pipe,
    a log) one progress line per interval instead (`IntervalProgress`)."""
    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    if remaining:
        columns.append(TimeRemainingColumn())
    return IntervalProgress(*columns, console=console, transient=True)


# -- progress that suits a terminal and a log alike ---------------------------------------------------------
# On a terminal a long command draws rich's live bar. Into a pipe or a file (a batch job's log, nohup, CI)
# a bar is noise and nothing is hours of silence: there `IntervalProgress` writes one plain line every
# interval instead, with what the bar shows.

PROGRESS_SECONDS = 30.0
"""Seconds between two progress lines off a terminal (``DATAGEN_PROGRESS_SECONDS`` overrides)."""


def progress_seconds() -> float:
    """The interval between progress lines off a terminal, from the environment or `PROGRESS_SECONDS`."""
    try:
        value = float(os.environ.get("DATAGEN_PROGRESS_SECONDS", PROGRESS_SECONDS))
    except ValueError:
        return PROGRESS_SECONDS
    return value if value > 0 else PROGRESS_SECONDS


class IntervalProgress(Progress):
    """A rich `Progress` that, when its live display is off (not a terminal), logs a line per interval
    to ``log`` (standard error by default: standard output keeps only results, such as ``--json``'s)."""

    def __init__(
        self,
        *columns: Any,
        console: Console,
        interval: float | None = None,
        log: Console | None = None,
        **kwargs: Any,
    ) -> None:
        self.logs = not console.is_terminal
        super().__init__(*columns, console=console, disable=self.logs, **kwargs)
        self.interval = progress_seconds() if interval is None else interval
        self.log_console = error_console if log is None else log
        self._last = self.get_time()

    def update(self, task_id: TaskID, **kwargs: Any) -> None:
        super().update(task_id, **kwargs)
        self._log()

    def advance(self, task_id: TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._log()

    def _log(self) -> None:
        if not self.logs or self.get_time() - self._last < self.interval:
            return
        self._last = self.get_time()
        for task in self.tasks:
            self.log_console.print(progress_line(task), markup=False, highlight=False, soft_wrap=True)


def progress_line(task: Task) -> str:
    """``tasks: 812/1,368 (59 %), 41,233 samples, 0 failed; 5.1 a second, about 1 min 49 s left``."""
    done = int(task.completed)
    parts = [f"{task.description}: {done:,}" + (f"/{int(task.total):,}" if task.total else "")]
    if task.total:
        parts[0] += f" ({100 * task.completed / task.total:.0f} %)"
    parts += [
        f"{value:,} {name}" if isinstance(value, int) else f"{value} {name}" for name, value in task.fields.items()
    ]
    line = ", ".join(parts)
    speed, left = task.speed, task.time_remaining
    if speed:
        line += f"; {speed:.3g} a second"
        if left is not None:
            line += f", about {duration(left)} left"
    return line


def duration(seconds: float) -> str:
    """``45 s``, ``3 min 20 s``, ``2 h 05 min``."""
    whole = max(0, round(seconds))
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        return f"{whole // 60} min {whole % 60} s"
    return f"{whole // 3600} h {(whole % 3600) // 60:02d} min"
