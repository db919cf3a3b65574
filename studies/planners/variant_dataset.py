"""Build the dataset of the learning curve's variants point: N real objects plus a seeded variant of each.

    python -m studies.planners.variant_dataset --data URL --objects-file FILE --config FILE --count 20 --out DIR
        [--seed 0]

The N objects are those the learning curve's ``objects-N`` point trains on (the same seeded, nested
draw as `osvp train --max-objects N --split objects --val-fraction 0.07`), so "N real + N variants"
is compared with ``objects-2N``, which holds those N and N more real ones. Their tasks are copied
from the source dataset (a task is a self-contained shard, index fragment and commit record, so the
copy is the dataset a generation of them would write), then `datagen submit` adds one variant of each
object (`datagen objects variants --count 1`) into the same folder: the copied tasks count as done.
Prints the objects file of the job and the command it ran.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
from pathlib import Path
from typing import cast

import numpy as np
from osvp.data import SampleBank, split_rows, training_subset

import storage
from datagen.pipeline.objects.objects_file import read_objects_file


class IndexOnly:
    """What the split and the draw read of a bank (the objects of its samples), from the index alone,
    without reading every sample's points."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.object_ids = tuple(storage.open_dataset(url).index.column("object_id").to_pylist())

    def __len__(self) -> int:
        return len(self.object_ids)


def chosen_objects(url: str, count: int, seed: int, val_fraction: float) -> set[str]:
    bank = cast(SampleBank, IndexOnly(url))
    train, _ = split_rows(bank, "objects", val_fraction, seed)
    rows = training_subset(bank, train, count, 1.0, seed)
    return {bank.object_ids[i] for i in np.asarray(rows).tolist()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--objects-file", type=Path, required=True, help="the objects file the dataset was made from")
    parser.add_argument("--count", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--val-fraction", type=float, default=0.07)
    parser.add_argument("--config", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    wanted = chosen_objects(args.data, args.count, args.seed, args.val_fraction)
    listing = read_objects_file(args.objects_file)
    lines = args.objects_file.read_text().splitlines()
    kept = [lines[spec.line - 1] for spec in listing.objects if spec.object_id in wanted]
    assert len(kept) == len(wanted), "an object of the dataset is not in the objects file"
    args.out.mkdir(parents=True, exist_ok=True)
    base = args.out / "base-objects.txt"
    base.write_text("\n".join(_absolute(line, args.objects_file.parent) for line in kept) + "\n")
    objects = args.out / "objects.txt"
    subprocess.run(["datagen", "objects", "variants", str(base), "--count", "1", "--out", str(objects)], check=True)

    source, target = Path(args.data), args.out / "data"
    (target / "commits").mkdir(parents=True, exist_ok=True)
    (target / "shards").mkdir(exist_ok=True)
    shutil.copy2(source / "dataset.json", target / "dataset.json")
    for record in storage.committed_tasks(storage.open_location(str(source))):
        if any(record.task_id.startswith(o[:16]) for o in wanted):
            shutil.copy2(source / "commits" / f"{record.task_id}.json", target / "commits" / f"{record.task_id}.json")
            shutil.copytree(source / "shards" / record.task_id, target / "shards" / record.task_id, dirs_exist_ok=True)
    command = ["datagen", "submit", "--objects", str(objects), "--config", str(args.config), "--out", str(target)]
    print(objects)
    print(" ".join(command))
    subprocess.run(command, check=True)


def _absolute(line: str, folder: Path) -> str:
    """An objects-file line with its (relative) path made absolute, so the line works from anywhere."""
    path, _, rest = line.partition(" ")
    if path.startswith("builtin:") or Path(path).is_absolute():
        return line
    return f"{(folder / path).resolve()} {rest}".strip()


if __name__ == "__main__":
    main()
