"""Reading and writing datasets on any fsspec URL: Zarr v3 shards, a Parquet index, commit records.

Depends on numpy, zarr, pyarrow, fsspec and `schemas` only: a training package needs nothing else
(``storage.torch`` adds PyTorch, imported only when that module is).
"""

from storage.dataset_info import init_dataset, read_info
from storage.location import Location, StorageError, open_location
from storage.reader import Dataset, finalise, open_dataset
from storage.validate import validate
from storage.writer import ShardPayload, committed_tasks, read_failures, write_failure, write_task

__all__ = [
    "Dataset",
    "Location",
    "ShardPayload",
    "StorageError",
    "committed_tasks",
    "finalise",
    "init_dataset",
    "open_dataset",
    "open_location",
    "read_failures",
    "read_info",
    "validate",
    "write_failure",
    "write_task",
]
