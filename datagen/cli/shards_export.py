"""``datagen shards export``: a dataset in one of the file layouts the authors' trainers read.

A plain function; `datagen.cli.shards` registers it. The layouts come from `storage.export.LAYOUTS`
(``--help`` lists them), and every value is checked there, so a bad one (unknown layout, ``--points``
<= 0, a non-empty OUT, ...) is one ``error:`` line, exit 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import dataset_options, lazy_help, progress_bar, say, user_errors


def layout_help() -> str:
    """``--layout``'s help, from the layout registry (imported only when help is shown)."""
    from storage.export import LAYOUTS

    return "Output layout: " + "; ".join(f"'{name}': {layout.summary}" for name, layout in LAYOUTS.items()) + "."


ExportCommand = lazy_help(layout=layout_help)


def export(
    url: Annotated[str, typer.Argument(metavar="URL", help="Dataset: a local path or an fsspec URL.")],
    out: Annotated[
        Path,
        typer.Argument(
            metavar="OUT",
            help="A new or empty output folder (for air its path must not contain 'cloud', for mascvp 'grid').",
        ),
    ],
    layout: Annotated[str, typer.Option("--layout", help="Output layout: see --help.")],
    points: Annotated[
        int | None,
        typer.Option("--points", help="Points per cloud (sampled, seeded; at least 2): air needs it, pcnbv 512."),
    ] = None,
    gt_points: Annotated[
        int | None, typer.Option("--gt-points", help="pcnbv: points per ground-truth cloud (default 16384).")
    ] = None,
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
    """Write every sample the layout's trainer can take, as the authors' generator names its files
    (<obj>/rotate_<k>/..._<c>.txt) plus the arrays their trainers load, train_split and test_split;
    the samples it cannot take are skipped and counted. Prints, and writes to PROVENANCE.md and
    provenance.json, every choice that differs from the authors'."""
    from storage.export import export as export_layout

    with user_errors(url):
        options = dataset_options(url)
        with progress_bar(remaining=True) as bar:
            task = bar.add_task("exporting samples", total=None)
            summary = export_layout(
                layout,
                url,
                out,
                num_points=points,
                gt_points=gt_points,
                seed=seed,
                val_fraction=val,
                rotation_names=rotation_names,
                storage_options=options,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )
        for line in summary.lines:
            say(line)
