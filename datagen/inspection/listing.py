"""What a dataset holds, task by task (``shards ls``) and sample by sample (``shards show``).

Everything is read from the dataset URL alone: the manifest (or the commit records) and the index say
what was written, failure records say what is missing and why, and the records' sizes (or, for
records written before they kept them, one listing of ``shards/``) give the bytes on disk.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from datagen.errors import InvalidArgument
from storage import Dataset, LabelAmbiguity, NextView, stored_bytes
from storage.samples import mask_bits

COMMITTED = "committed"
FAILED = "failed"

_ROTATION = re.compile(r"-r(\d+)$")
_ROW_NUMBER = re.compile(r"\d+")


@dataclass(frozen=True)
class TaskRow:
    """One task of a dataset: what it stored, or why it stored nothing."""

    task_id: str
    object_name: str
    rotation: int | None
    """None for a failure that is not a task (an objects-file line that could not be read)."""
    samples: int
    points: int
    """Points of every stored refined cloud P(O_S) of the task, summed."""
    bytes_on_disk: int
    """Bytes of the committed shard group and index fragment (orphaned attempts excluded)."""
    state: str
    """`COMMITTED` or `FAILED`."""
    origin: str = ""
    message: str = ""

    def sort_key(self) -> tuple[str, int, str]:
        return (self.object_name, -1 if self.rotation is None else self.rotation, self.task_id)


def rotation_of(task_id: str) -> int | None:
    """The rotation a task id ends with (``<object>-r<rotation>``); None for other failure ids."""
    match = _ROTATION.search(task_id)
    return int(match.group(1)) if match else None


def list_tasks(dataset: Dataset) -> list[TaskRow]:
    """Every committed task and every failed one, sorted by object name, rotation and task id."""
    commits = dataset.task_records()
    if all(record.stored_bytes is not None for record in commits):
        sizes = {record.task_id: int(record.stored_bytes or 0) for record in commits}
    else:  # records from before the one-file layout: one listing of shards/ says
        sizes = stored_bytes(dataset.location, commits)
    per_task = _index_totals(dataset)
    rows = []
    for record in commits:
        totals = per_task.get(record.task_id)
        if totals is None:  # a task whose every case was dropped: names come from its shard
            attributes = dataset.shard(record.shard).attributes
            totals = {"object_name": attributes.object_name, "rotation": attributes.rotation, "samples": 0, "points": 0}
        rows.append(
            TaskRow(
                task_id=record.task_id,
                object_name=str(totals["object_name"]),
                rotation=int(totals["rotation"]),
                samples=int(totals["samples"]),
                points=int(totals["points"]),
                bytes_on_disk=sizes.get(record.task_id, 0),
                state=COMMITTED,
            )
        )
    rows += failed_tasks(dataset, {record.task_id for record in commits})
    return sorted(rows, key=TaskRow.sort_key)


def failed_tasks(dataset: Dataset, committed: set[str]) -> list[TaskRow]:
    """Tasks with a failure record and no commit, sorted (a stale failure record of a task that
    committed later does not count: readers follow commits, so its samples are there)."""
    rows = [
        TaskRow(
            task_id=failure.task_id,
            object_name=failure.object_name,
            rotation=rotation_of(failure.task_id),
            samples=0,
            points=0,
            bytes_on_disk=0,
            state=FAILED,
            origin=failure.origin,
            message=failure.message,
        )
        for failure in dataset.failures()
        if failure.task_id not in committed
    ]
    return sorted(rows, key=TaskRow.sort_key)


def _index_totals(dataset: Dataset) -> dict[str, dict[str, Any]]:
    """Samples and summed points per task id: from the manifest's tasks table and one numeric column
    (points summed by the samples' task), else grouped over the index columns."""
    tasks = dataset.task_table()
    if tasks is not None and dataset.samples.positions is None:
        counts = np.asarray(tasks.column("num_samples").to_pylist(), dtype=np.int64)
        names = tasks.column("object_name").to_pylist()
        if all(name is not None for name, count in zip(names, counts.tolist(), strict=True) if count):
            points = np.bincount(dataset.samples.codes, weights=dataset.values("num_points"), minlength=tasks.num_rows)
            ids, rotations = tasks.column("task_id").to_pylist(), tasks.column("rotation").to_pylist()
            return {
                task: {"object_name": name, "rotation": rotation, "samples": int(count), "points": int(total)}
                for task, name, rotation, count, total in zip(
                    ids, names, rotations, counts.tolist(), points.tolist(), strict=True
                )
                if count
            }
    return _grouped_totals(dataset)


def _grouped_totals(dataset: Dataset) -> dict[str, dict[str, Any]]:
    """Samples and summed points per task id, in one pass over the index columns."""
    columns = ["task_id", "object_name", "rotation", "num_points"]
    # use_threads=False: pyarrow's thread pool must not outlive the command (it aborts at exit).
    grouped = (
        pa.table({name: dataset.column(name) for name in columns})
        .group_by(["task_id", "object_name", "rotation"], use_threads=False)
        .aggregate([("num_points", "sum"), ("num_points", "count")])
    )
    totals: dict[str, dict[str, Any]] = {}
    for row in grouped.to_pylist():
        totals[row["task_id"]] = {
            "object_name": row["object_name"],
            "rotation": row["rotation"],
            "samples": row["num_points_count"],
            "points": row["num_points_sum"],
        }
    return totals


# -- one sample ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SampleDetails:
    """One sample as ``shards show`` prints it: index metadata, its views (read from the shard) and
    the sizes of its stored clouds."""

    row: int
    metadata: dict[str, Any]
    """The sample's index row (every `INDEX_SCHEMA` column)."""
    input_views: tuple[int, ...]
    label_views: tuple[int, ...]
    num_views: int
    points: int
    """Keys of the refined cloud P(O_S) stored in the shard."""
    observed: int
    """Keys of the observed cloud keys(O_S) stored in the shard."""
    ambiguity: LabelAmbiguity | None = None
    """The label's minimum covers, count and support (version-2 datasets)."""
    next_view: NextView | None = None
    """The gains and best next view (version-3 datasets)."""


def find_sample(dataset: Dataset, text: str) -> int:
    """The index row a user named, by row number or by sample id."""
    count = len(dataset)
    if _ROW_NUMBER.fullmatch(text):
        row = int(text)
        if row >= count:
            raise InvalidArgument(
                f"sample {row} out of range: {dataset.url} holds {count} samples (rows 0 to {count - 1})"
            )
        return row
    found = pc.index(dataset.column("sample_id"), text).as_py()
    if found < 0:
        raise InvalidArgument(
            f"no sample {text!r} in {dataset.url}; give a row number (0 to {count - 1}) or a sample id"
        )
    return int(found)


def describe_sample(dataset: Dataset, row: int) -> SampleDetails:
    """Index metadata plus what the shard itself holds for sample ``row``."""
    view_state, label = dataset.masks(row)
    width = dataset.num_views
    return SampleDetails(
        row=row,
        metadata=dataset.index_row(row),
        input_views=tuple(np.flatnonzero(mask_bits(view_state, width)).tolist()),
        label_views=tuple(np.flatnonzero(mask_bits(label, width)).tolist()),
        num_views=width,
        points=len(dataset.keys(row, "points")),
        observed=len(dataset.keys(row, "observed")),
        ambiguity=dataset.ambiguity(row) if dataset.has_ambiguity else None,
        next_view=dataset.next_view(row) if dataset.has_next_view else None,
    )
