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
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from schemas.dataset import CARD_FILE
from storage.export.base import Export, Layout, Place, Progress, Run, Writer
from storage.export.checks import check_output
from storage.export.folders import object_folders, rotation_folders
from storage.export.options import (
    PHRASES,
    PROVENANCE_JSON,
    PROVENANCE_MD,
    SPLITS,
    TEST,
    TEST_SPLIT,
    TRAIN,
    TRAIN_SPLIT,
    Options,
)
from storage.export.provenance import dataset_facts, frame_facts, markdown, rotation_facts, view_facts
from storage.export.publish import make_folder, make_staging, publish, write_text
from storage.export.registry import layout_named
from storage.readers.reader import Dataset, open_dataset
from storage.samples.splits import held_out_objects
from storage.store.location import StorageError


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
    if not plan.kept.size:
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
        _write_samples(dataset, plan, writer, chosen.fields, folders, rotations, staging, target, progress)
        writer.finish()
        provenance = _provenance(chosen, dataset, options, plan, rotations, writer.lines(), writer.facts())
        _write_text_files(staging, target, chosen, plan, provenance)
        if dataset.location.exists(CARD_FILE):  # the dataset card travels with the data
            write_text(staging / CARD_FILE, dataset.location.read_bytes(CARD_FILE).decode(), target)
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
    """Which rows are written, each one's split, and the object folders on each side: arrays over the
    rows (a dataset of millions of samples holds no Python object per sample)."""

    kept: npt.NDArray[np.int64]
    """Rows written, ascending."""
    side_of: npt.NDArray[np.int8]
    """Per row: its split's place in `SPLITS`, or -1 where it is skipped."""
    object_codes: npt.NDArray[np.int64]
    """Per row: its object's place in ``object_ids``."""
    object_ids: list[str]
    skipped: dict[str, str]
    """Sample id -> why it is not written."""
    train_names: list[str]
    test_names: list[str]

    @classmethod
    def of(cls, dataset: Dataset, reasons: list[str], options: Options, folders: dict[str, str]) -> _Plan:
        encoded = pc.dictionary_encode(dataset.samples.column("object_id", keep=False)).combine_chunks()
        object_ids = encoded.dictionary.to_pylist()
        codes = encoded.indices.to_numpy(zero_copy_only=False).astype(np.int64)
        written = np.fromiter((not reason for reason in reasons), dtype=bool, count=len(reasons))
        kept = np.flatnonzero(written)
        dropped = np.flatnonzero(~written)
        ids = dataset.samples.column("sample_id", keep=False).take(pa.array(dropped)).to_pylist()
        skipped = dict(sorted(zip(ids, (reasons[i] for i in dropped.tolist()), strict=True)))
        # `split_by_object` over the kept rows' objects, decided once per object instead of per row.
        present = sorted({object_ids[c] for c in np.unique(codes[kept]).tolist()})
        held = held_out_objects(present, options.val_fraction, options.seed)
        in_test = np.fromiter((o in held for o in object_ids), dtype=bool, count=len(object_ids))
        side_of = np.full(len(reasons), -1, dtype=np.int8)
        side_of[kept] = np.where(in_test[codes[kept]], SPLITS.index(TEST), SPLITS.index(TRAIN))
        names = {}
        for side in SPLITS:
            on_side = np.unique(codes[side_of == SPLITS.index(side)]).tolist()
            names[side] = sorted({folders[object_ids[c]] for c in on_side})
        return cls(kept, side_of, codes, object_ids, skipped, names[TRAIN], names[TEST])

    def sizes(self) -> dict[str, int]:
        counts = np.bincount(self.side_of[self.side_of >= 0], minlength=len(SPLITS))
        return {side: int(counts[k]) for k, side in enumerate(SPLITS)}


def _write_samples(
    dataset: Dataset,
    plan: _Plan,
    writer: Writer,
    fields: tuple[str, ...],
    folders: dict[str, str],
    rotations: dict[int, str],
    staging: Path,
    target: Path,
    progress: Progress | None,
) -> None:
    """Every sample in shard order (shards sorted by path, rows in index order): the written ones get
    their place and their ``fields`` (`Dataset.sample`), every one counts for the progress. Sample ids
    are read a shard's rows at a time."""
    sample_id_column = dataset.samples.column("sample_id", keep=False)
    rotation_of = dataset.values("rotation", keep=False)
    rows = dataset.values("row", keep=False)
    positions = dict.fromkeys(SPLITS, 0)
    made: set[Path] = set()
    done = 0
    for block in dataset.shard_blocks():
        sides = plan.side_of[block]
        chosen = block[sides >= 0]
        sample_ids = dict(zip(chosen.tolist(), sample_id_column.take(pa.array(chosen)).to_pylist(), strict=True))
        for i, code in zip(block.tolist(), sides.tolist(), strict=True):
            done += 1
            if code >= 0:
                side = SPLITS[code]
                folder = staging / folders[plan.object_ids[plan.object_codes[i]]] / rotations[int(rotation_of[i])]
                if folder not in made:
                    make_folder(folder, target)
                    made.add(folder)
                place = Place(i, sample_ids[i], folder, int(rows[i]), side, positions[side])
                writer.write(place, dataset.sample(i, fields))
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
