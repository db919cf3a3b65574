"""Reading and writing datasets on any fsspec URL: Zarr v3 shards, a Parquet index, commit records.

Depends on numpy, zarr, pyarrow, fsspec and `schemas` only: a training package needs nothing else
(``storage.torch`` adds PyTorch, imported only when that module is).
"""

from storage.dataset_info import init_dataset, read_info
from storage.export import export_air
from storage.location import Location, StorageError, is_s3, open_location, storage_failure
from storage.reader import Dataset, finalise, load_index, open_dataset
from storage.shards import ShardReader
from storage.validate import SAMPLED_ROWS_PER_SHARD, validate
from storage.writer import (
    ShardPayload,
    committed_tasks,
    holds_dataset,
    read_commit,
    read_commits,
    read_failures,
    stored_bytes,
    write_failure,
    write_task,
)

__all__ = [
    "SAMPLED_ROWS_PER_SHARD",
    "Dataset",
    "Location",
    "ShardPayload",
    "ShardReader",
    "StorageError",
    "committed_tasks",
    "export_air",
    "finalise",
    "holds_dataset",
    "init_dataset",
    "is_s3",
    "load_index",
    "open_dataset",
    "open_location",
    "read_commit",
    "read_commits",
    "read_failures",
    "read_info",
    "storage_failure",
    "stored_bytes",
    "validate",
    "write_failure",
    "write_task",
]
