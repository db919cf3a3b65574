"""``datagen shards export``: a dataset in the authors' (AIR-OSVP) text layout.

A plain function; `datagen.cli.shards` registers it. Every value is checked by `storage.export`, so a
bad one (unknown layout, ``--points`` <= 0, a non-empty OUT, ...) is one ``error:`` line, exit 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import dataset_options, progress_bar, say, user_errors


def export(
    url: Annotated[str, typer.Argument(metavar="URL", help="Dataset: a local path or an fsspec URL.")],
    out: Annotated[
        Path, typer.Argument(metavar="OUT", help="A new or empty output folder (its path must not contain 'cloud').")
    ],
    layout: Annotated[str, typer.Option("--layout", help="Output layout: 'air' (AIR-OSVP text files).")],
    points: Annotated[int, typer.Option("--points", help="Points per cloud (sampled, seeded; at least 2).")],
    seed: Annotated[int, typer.Option("--seed", help="Seeds point sampling and the split.")] = 0,
    val: Annotated[float, typer.Option("--val", help="Fraction of objects in test_split (0 to 1).")] = 0.2,
    rotation_names: Annotated[
        str,
        typer.Option(
            "--rotation-names",
            help="'authors': rotate_<k> = yaw 45 deg x k (refused where an angle has no k); "
            "'yaw': folders yaw_<degrees>.",
        ),
    ] = "authors",
) -> None:
    """Write every sample in the authors' text layout (<obj>/rotate_<k>/cloud_<i>.txt, state_<i>.txt,
    ids_<i>.txt, train_split, test_split) so AIR-OSVP's trainer reads it unchanged; samples with an
    empty label or no points are skipped. Prints, and writes to PROVENANCE.md and provenance.json,
    every choice that differs from the authors'."""
    from storage import export_air
    from storage.export import check_layout

    with user_errors(url):
        check_layout(layout)
        options = dataset_options(url)
        with progress_bar(remaining=True) as bar:
            task = bar.add_task("exporting samples", total=None)
            summary = export_air(
                url,
                out,
                num_points=points,
                seed=seed,
                val_fraction=val,
                rotation_names=rotation_names,
                storage_options=options,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )
        for line in summary.lines:
            say(line)
