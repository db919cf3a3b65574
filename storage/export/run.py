"""One export, whatever its layout: check, choose what to write, split by object, write sample by
sample (shard by shard, so each shard is read once), then the split and provenance files, and publish.

Which samples a layout skips is decided from the index before anything is written, so the split and
every sample's row in its split's arrays are known up front and arrays are filled in place.
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from storage.export.common import (
    PHRASES,
    PROVENANCE_JSON,
    PROVENANCE_MD,
    SPLITS,
    TEST,
    TEST_SPLIT,
    TRAIN,
    TRAIN_SPLIT,
    Export,
    Layout,
    Options,
    Place,
    Progress,
    Run,
    Writer,
    check_output,
    dataset_facts,
    frame_facts,
    make_folder,
    make_staging,
    markdown,
    object_folders,
    publish,
    rotation_facts,
    rotation_folders,
    view_facts,
    write_text,
)
from storage.export.registry import layout_named
from storage.location import StorageError
from storage.reader import Dataset, open_dataset
from storage.samples import split_by_object


def export(
    layout: str,
    url: str,
    out: str | Path,
    *,
    num_points: int | None = None,
    gt_points: int | None = None,
    seed: int = 0,
    val_fraction: float = 0.2,
    rotation_names: str = "authors",
    progress: Progress | None = None,
    storage_options: dict[str, Any] | None = None,
) -> Export:
    """Write every sample of the dataset at ``url`` that layout ``layout`` can take into the new or empty
    folder ``out``.

    Raises `StorageError` (one line naming the fix) for an unknown layout, bad options, an output folder
    that is not new or empty or whose path holds the word the layout's loader replaces, a dataset that
    cannot be read, has other than 32 views or (for the next-view layouts) is older than schema version
    3, rotations without an authors' folder, and a split that leaves ``train_split`` empty.
    """
    chosen = layout_named(layout)
    options = chosen.resolve(Options(num_points, gt_points, seed, val_fraction, rotation_names))
    target = check_output(Path(out), chosen.path_word)
    dataset = open_dataset(url, storage_options)
    chosen.check_dataset(dataset)
    if len(dataset) == 0:
        raise StorageError(f"{url}: holds no samples; there is nothing to export")
    folders = object_folders(dataset, chosen.name_word, chosen.reserved)
    rotations = rotation_folders(dataset, options.rotation_names)
    reasons = chosen.skipped(dataset)
    plan = _Plan.of(dataset, reasons, options, folders)
    if not plan.kept:
        why = " or ".join(PHRASES[reason] for reason in chosen.skip_reasons)
        raise StorageError(f"{url}: every sample has {why}; there is nothing the authors' trainer can read")
    if not plan.train_names:
        raise StorageError(
            f"--val {options.val_fraction}: leaves train_split empty ({len(plan.test_names)} objects in all); "
            "their trainer trains on train_split objects only, so lower --val"
        )
    staging = make_staging(target)
    try:
        writer = chosen.start(Run(dataset, staging, target, options, plan.sizes()))
        _write_samples(dataset, plan, writer, folders, rotations, staging, target, progress)
        writer.finish()
        provenance = _provenance(chosen, dataset, options, plan, rotations, writer.lines(), writer.facts())
        _write_text_files(staging, target, chosen, plan, provenance)
        publish(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    total = len(dataset)
    lines = (f"exported {len(plan.kept)} samples to {target} (of {total} in the dataset)", *provenance["lines"][1:])
    return Export(
        out=target,
        layout=chosen.name,
        samples=total,
        written=len(plan.kept),
        skipped=plan.skipped,
        train_objects=tuple(plan.train_names),
        test_objects=tuple(plan.test_names),
        lines=lines,
        provenance=provenance,
    )


@dataclass(frozen=True)
class _Plan:
    """Which rows are written, each one's split, and the object folders on each side."""

    kept: list[int]
    split_of: dict[int, str]
    skipped: dict[str, str]
    """Sample id -> why it is not written."""
    train_names: list[str]
    test_names: list[str]

    @classmethod
    def of(cls, dataset: Dataset, reasons: list[str], options: Options, folders: dict[str, str]) -> _Plan:
        sample_ids = dataset.column("sample_id").to_pylist()
        objects = dataset.column("object_id").to_pylist()
        kept = [i for i, reason in enumerate(reasons) if not reason]
        skipped = dict(sorted((sample_ids[i], reason) for i, reason in enumerate(reasons) if reason))
        train_at, test_at = split_by_object([objects[i] for i in kept], options.val_fraction, options.seed)
        split_of = {kept[p]: TRAIN for p in train_at.tolist()} | {kept[p]: TEST for p in test_at.tolist()}
        names = {side: sorted({folders[objects[i]] for i, s in split_of.items() if s == side}) for side in SPLITS}
        return cls(kept, split_of, skipped, names[TRAIN], names[TEST])

    def sizes(self) -> dict[str, int]:
        counts = Counter(self.split_of.values())
        return {side: counts.get(side, 0) for side in SPLITS}


def _write_samples(
    dataset: Dataset,
    plan: _Plan,
    writer: Writer,
    folders: dict[str, str],
    rotations: dict[int, str],
    staging: Path,
    target: Path,
    progress: Progress | None,
) -> None:
    """Every sample in shard order (shards sorted by path, rows in index order): the written ones get
    their place, every one counts for the progress."""
    sample_ids = dataset.column("sample_id").to_pylist()  # one column at a time, never the whole index
    objects = dataset.column("object_id").to_pylist()
    rotation_of = dataset.values("rotation")
    rows = dataset.values("row")
    positions = dict.fromkeys(SPLITS, 0)
    made: set[Path] = set()
    order = np.concatenate(dataset.shard_blocks()).tolist()
    for done, i in enumerate(order, 1):
        side = plan.split_of.get(i)
        if side is not None:
            folder = staging / folders[objects[i]] / rotations[int(rotation_of[i])]
            if folder not in made:
                make_folder(folder, target)
                made.add(folder)
            writer.write(Place(i, sample_ids[i], folder, int(rows[i]), side, positions[side]))
            positions[side] += 1
        if progress is not None:
            progress(done, len(dataset))


def _provenance(
    layout: Layout,
    dataset: Dataset,
    options: Options,
    plan: _Plan,
    rotations: dict[int, str],
    layout_lines: list[str],
    layout_facts: dict[str, Any],
) -> dict[str, Any]:
    counts = Counter(plan.skipped.values())
    skip_lines = [
        f"skipped {counts.get(reason, 0)} samples with {PHRASES[reason]} ({why})"
        for reason, why in layout.skip_reasons.items()
    ]
    dataset_line, dataset_data = dataset_facts(dataset)
    note = layout.dataset_note(dataset)
    frame_line, frame_data = frame_facts(dataset)
    rotation_line, rotation_data = rotation_facts(dataset, options.rotation_names, rotations)
    views_line, views_data = view_facts(dataset)
    split_line = (
        f"split: train_split {len(plan.train_names)} objects, test_split {len(plan.test_names)} (by object, "
        f"val {options.val_fraction:g}, seed {options.seed}, as storage's Dataset.split); {layout.split_use}"
    )
    lines = [
        f"exported {len(plan.kept)} samples (of {len(dataset)} in the dataset)",
        *skip_lines,
        f"{dataset_line}; {note}" if note else dataset_line,
        *layout_lines,
        frame_line,
        rotation_line,
        views_line,
        split_line,
        f"provenance: {PROVENANCE_MD} and {PROVENANCE_JSON} in the export",
    ]
    skipped: dict[str, Any] = {reason.replace(" ", "_"): counts.get(reason, 0) for reason in layout.skip_reasons}
    skipped["samples"] = plan.skipped
    return {
        "layout": layout.name,
        "read_by": layout.read_by,
        "dataset": dataset_data,
        "written": len(plan.kept),
        "skipped": skipped,
        **layout_facts,
        "frame": frame_data,
        "rotations": rotation_data,
        "views": views_data,
        "split": {
            "val_fraction": options.val_fraction,
            "seed": options.seed,
            "by": "object (storage Dataset.split over the written samples)",
            "train_split": plan.train_names,
            "test_split": plan.test_names,
            "authors_use": layout.split_use,
        },
        "lines": lines,
    }


def _write_text_files(staging: Path, target: Path, layout: Layout, plan: _Plan, provenance: dict[str, Any]) -> None:
    write_text(staging / TRAIN_SPLIT, "".join(f"{name}\n" for name in plan.train_names), target)
    write_text(staging / TEST_SPLIT, "".join(f"{name}\n" for name in plan.test_names), target)
    write_text(staging / PROVENANCE_JSON, json.dumps(provenance, indent=1) + "\n", target)
    write_text(staging / PROVENANCE_MD, markdown(layout, provenance["lines"]), target)
