"""``datagen shards pack``: a finished dataset in a few large tar files with one manifest, for shipping.

A plain function; `datagen.cli.shards` registers it. The work is `storage.dataset.pack_dataset`; every
refusal (an unfinished or older-layout dataset, a non-empty OUT) is one ``error:`` line.
"""

from __future__ import annotations

from typing import Annotated

import typer

from datagen.cli.common import dataset_options, plural, progress_bar, say, user_errors
from schemas.dataset import PACK_BYTES

MIB = 1024**2


def pack(
    url: Annotated[str, typer.Argument(metavar="URL", help="A finalised dataset (one file per task, version 5).")],
    out: Annotated[str, typer.Option("--out", help="A new or empty location for the packed dataset.")],
    pack_mb: Annotated[
        int,
        typer.Option("--pack-mb", help="About this many MiB a pack (tar) file; WebDataset uses ~1 GB, MDS 64 MB."),
    ] = PACK_BYTES // MIB,
) -> None:
    """Write the dataset's tasks into tar files of about --pack-mb each (in task id order, each task its
    shard <task>.zarr.zip and index rows <task>.index.parquet: WebDataset shards) and one manifest; the
    packed dataset reads like the original (storage.open_dataset, the streaming reader, every shards
    command) and is read-only."""
    from storage.dataset import pack_dataset

    with user_errors(url):
        options = dataset_options(url)
        with progress_bar(remaining=True) as bar:
            task = bar.add_task("packing tasks", total=None)
            summary = pack_dataset(
                url,
                out,
                target_bytes=pack_mb * MIB,
                storage_options=options,
                progress=lambda p: bar.update(task, completed=p.tasks_done, total=p.tasks_total),
            )
    say(
        f"packed {plural(summary.tasks, 'task')} ({plural(summary.samples, 'sample')}, "
        f"{summary.bytes_written / MIB:.0f} MiB) into {plural(summary.packs, 'pack')} in {summary.seconds:.1f} s: "
        f"{summary.out}"
    )
