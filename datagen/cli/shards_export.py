"""``datagen shards export``: a dataset in the authors' (AIR-OSVP) text layout.

A plain function; `datagen.cli.shards` registers it.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import console, user_errors


class Layout(StrEnum):
    air = "air"


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
    from storage import export_air

    assert layout is Layout.air  # the only layout so far; typer refuses any other value
    with user_errors():
        count = export_air(url, out, num_points=points, seed=seed, val_fraction=val)
        console.print(f"exported {count} samples to {out.resolve()}", markup=False, highlight=False, soft_wrap=True)
