"""``datagen shards``: inspect, validate, relabel and export datasets (the group and ``export``).

Registered in ``datagen/cli/main.py`` with ``app.add_typer(shards_app, name="shards")``.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import EXIT_USER_ERROR, console, error_console, user_errors

shards_app = typer.Typer(help="Inspect, validate and export datasets.", no_args_is_help=True)


class Layout(StrEnum):
    air = "air"


@contextmanager
def storage_errors() -> Iterator[None]:
    """`user_errors`, extended to `storage.StorageError` (a dataset that cannot be read or written)."""
    from storage.location import StorageError

    with user_errors():
        try:
            yield
        except StorageError as exc:
            error_console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(EXIT_USER_ERROR) from None


@shards_app.command("export")
def export(
    url: Annotated[str, typer.Argument(metavar="URL", help="Dataset: a local path or an fsspec URL.")],
    out: Annotated[Path, typer.Argument(metavar="OUT", help="Output folder (its path must not contain 'cloud').")],
    layout: Annotated[Layout, typer.Option("--layout", help="Output layout: 'air' (AIR-OSVP text files).")],
    points: Annotated[int, typer.Option("--points", min=1, help="Points per cloud (sampled, seeded).")],
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seeds point sampling and the split.")] = 0,
    val: Annotated[float, typer.Option("--val", min=0.0, max=1.0, help="Fraction of objects in test_split.")] = 0.2,
) -> None:
    """Write every sample in the authors' text layout (<obj>/rotate_<r>/cloud_<i>.txt, state_<i>.txt,
    ids_<i>.txt, plus train_split and test_split), so AIR-OSVP's trainer reads it unchanged."""
    from storage.export import export_air

    assert layout is Layout.air  # the only layout so far; typer refuses any other value
    with storage_errors():
        count = export_air(url, out, num_points=points, seed=seed, val_fraction=val)
        console.print(f"exported {count} samples to {out.resolve()}", markup=False, highlight=False, soft_wrap=True)


# The other commands live in their own modules and register themselves on `shards_app`.
from datagen.cli import shards_check, shards_view  # noqa: E402, F401
