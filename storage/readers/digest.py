"""A dataset's content digest: one SHA-256 that two runs of the same job share exactly when they hold
the same samples, byte for byte, wherever and in whatever order their tasks ran.

It covers every committed task's shard arrays (which hold every sample's clouds, masks and labels) in
task-id order and every index column except the volatile ones (solver times, attempts, shard file
names) in sample-id order; each stored byte is read once. Why it exists: "reproducible" is a claim a
user can check (a local run against a cluster run, a run with faults against one without, a refactor
against the code before it).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from schemas.index import VOLATILE_COLUMNS
from schemas.shard import array_names
from storage.dataset import committed_tasks
from storage.readers.reader import open_dataset
from storage.shards import ShardReader

COLUMN_SLICE_ROWS = 65_536
"""Index rows turned into Python values at a time while hashing a column."""


@dataclass(frozen=True)
class Digest:
    """What `dataset_digest` found: the hex SHA-256 and the sample counts beside it."""

    sha256: str
    samples: int
    distinct_ids: int
    """Distinct sample ids: below ``samples`` only when a sample was written twice."""


def _feed(hasher: Any, name: str, value: object) -> None:
    """Hash a named value: an array by dtype, shape and bytes, anything else by its repr."""
    hasher.update(name.encode() + b"\0")
    if isinstance(value, np.ndarray):
        hasher.update(repr((value.dtype.str, value.shape)).encode())
        hasher.update(np.ascontiguousarray(value).tobytes())
    else:
        hasher.update(repr(value).encode())


def dataset_digest(url: str, storage_options: dict[str, Any] | None = None) -> Digest:
    """The content digest of the dataset at ``url`` (any fsspec URL)."""
    dataset = open_dataset(url, storage_options)
    hasher = hashlib.sha256()
    _feed(hasher, "schema_version", dataset.info.schema_version)
    for record in sorted(committed_tasks(dataset.location), key=lambda r: r.task_id):
        shard = ShardReader(dataset.location, record.shard)
        for name in array_names(dataset.info.schema_version):
            _feed(hasher, f"{record.task_id}/{name}", np.asarray(shard.array(name)))
    columns = [name for name in dataset.index.column_names if name not in VOLATILE_COLUMNS]
    table = dataset.index.select(columns).sort_by("sample_id")
    for name in columns:
        _feed_column(hasher, f"index/{name}", table.column(name))
    distinct = pc.count_distinct(dataset.index.column("sample_id")).as_py()
    return Digest(hasher.hexdigest(), dataset.index.num_rows, distinct)


def _feed_column(hasher: Any, name: str, column: pa.ChunkedArray) -> None:
    """Hash a column as `_feed` hashes its whole Python list (the same bytes: the list's repr), a slice
    of rows at a time, so a million-row index never becomes one Python list or one string."""
    hasher.update(name.encode() + b"\0" + b"[")
    first = True
    for chunk in column.chunks:
        for start in range(0, len(chunk), COLUMN_SLICE_ROWS):
            values = chunk.slice(start, COLUMN_SLICE_ROWS).to_pylist()
            if values:
                hasher.update(((", " if not first else "") + ", ".join(map(repr, values))).encode())
                first = False
    hasher.update(b"]")
