"""Reading and writing datasets on any fsspec URL: Zarr v3 shards, a Parquet index, commit records.

Depends on numpy, zarr, pyarrow, fsspec and `schemas` only: a training package needs nothing else
(``storage.torch`` adds PyTorch, imported only when that module is).
"""

from storage.covers import covers_universe, nearest_cover, undominated, universe_rows
from storage.dataset_info import existing_info, init_dataset, read_info
from storage.export import export_air
from storage.index import load_index
from storage.location import DamagedFile, Location, StorageError, StoreUnreachable, is_s3, open_location
from storage.problems import Mend, Problem
from storage.reader import Dataset, LabelAmbiguity, NextView, finalise, open_dataset
from storage.shards import ShardReader
from storage.store_errors import check_store, is_store_failure, is_transient, storage_failure, store_errors
from storage.validate import SAMPLED_ROWS_PER_SHARD, Validation, validate, validate_dataset
from storage.writer import (
    ShardPayload,
    committed_tasks,
    holds_dataset,
    read_commit,
    read_commits,
    read_failures,
    stored_bytes,
    sweep_orphans,
    sweep_temporaries,
    write_failure,
    write_task,
)

__all__ = [
    "SAMPLED_ROWS_PER_SHARD",
    "DamagedFile",
    "Dataset",
    "LabelAmbiguity",
    "Location",
    "Mend",
    "NextView",
    "Problem",
    "ShardPayload",
    "ShardReader",
    "StorageError",
    "StoreUnreachable",
    "Validation",
    "check_store",
    "committed_tasks",
    "covers_universe",
    "existing_info",
    "export_air",
    "finalise",
    "holds_dataset",
    "init_dataset",
    "is_s3",
    "is_store_failure",
    "is_transient",
    "load_index",
    "nearest_cover",
    "open_dataset",
    "open_location",
    "read_commit",
    "read_commits",
    "read_failures",
    "read_info",
    "storage_failure",
    "store_errors",
    "stored_bytes",
    "sweep_orphans",
    "sweep_temporaries",
    "undominated",
    "universe_rows",
    "validate",
    "validate_dataset",
    "write_failure",
    "write_task",
]
