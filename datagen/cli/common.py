"""What every command shares: the consoles, the one user-error handler, shared option types.

Command modules import this module and nothing else from `datagen.cli`; `datagen.cli.main` (and
`datagen.cli.shards` for its group) register their plain functions.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

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


def dataset_options(url: str) -> dict[str, Any]:
    """fsspec options of a dataset URL: the bounded timeouts and retries of `RunSettings`."""
    from datagen.settings import RunSettings

    return RunSettings().storage_options(url)


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
    a log) one progress line per interval instead (`datagen.cli.progress.IntervalProgress`)."""
    from datagen.cli.progress import IntervalProgress

    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    if remaining:
        columns.append(TimeRemainingColumn())
    return IntervalProgress(*columns, console=console, transient=True)
