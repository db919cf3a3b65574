"""What every command shares: one-line user errors, the console, bounded BLAS threads."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import typer
from rich.console import Console

from datagen.errors import DatagenError

console = Console()
error_console = Console(stderr=True)

EXIT_USER_ERROR = 2


@contextmanager
def user_errors() -> Iterator[None]:
    """Print a user-caused error as one line and exit non-zero; bugs keep their traceback."""
    try:
        yield
    except DatagenError as exc:
        error_console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(EXIT_USER_ERROR) from None
