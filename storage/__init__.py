"""Reading and writing datasets on any fsspec URL: Zarr v3 shards, a Parquet index, commit records.

Depends on numpy, zarr, pyarrow, fsspec and `schemas` only: a training package needs nothing else
(``storage.torch`` adds PyTorch, imported only when that module is).
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.covers import covers_universe, nearest_cover, undominated, universe_rows
    from storage.dataset_info import existing_info, init_dataset, read_info
    from storage.export import export_air
    from storage.index import load_index
    from storage.location import DamagedFile, Location, StorageError, StoreUnreachable, is_s3, open_location
    from storage.problems import Mend, Problem
    from storage.reader import Dataset, LabelAmbiguity, NextView, finalise, open_dataset
    from storage.shards import ShardReader
    from storage.store_errors import check_store, is_store_failure, is_transient, storage_failure, store_errors
    from storage.validation import SAMPLED_ROWS_PER_SHARD, Validation, validate, validate_dataset
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

_HOMES = {
    "covers_universe": "storage.covers",
    "nearest_cover": "storage.covers",
    "undominated": "storage.covers",
    "universe_rows": "storage.covers",
    "existing_info": "storage.dataset_info",
    "init_dataset": "storage.dataset_info",
    "read_info": "storage.dataset_info",
    "export_air": "storage.export",
    "load_index": "storage.index",
    "DamagedFile": "storage.location",
    "Location": "storage.location",
    "StorageError": "storage.location",
    "StoreUnreachable": "storage.location",
    "is_s3": "storage.location",
    "open_location": "storage.location",
    "Mend": "storage.problems",
    "Problem": "storage.problems",
    "Dataset": "storage.reader",
    "LabelAmbiguity": "storage.reader",
    "NextView": "storage.reader",
    "finalise": "storage.reader",
    "open_dataset": "storage.reader",
    "ShardReader": "storage.shards",
    "check_store": "storage.store_errors",
    "is_store_failure": "storage.store_errors",
    "is_transient": "storage.store_errors",
    "storage_failure": "storage.store_errors",
    "store_errors": "storage.store_errors",
    "SAMPLED_ROWS_PER_SHARD": "storage.validation",
    "Validation": "storage.validation",
    "validate": "storage.validation",
    "validate_dataset": "storage.validation",
    "ShardPayload": "storage.writer",
    "committed_tasks": "storage.writer",
    "holds_dataset": "storage.writer",
    "read_commit": "storage.writer",
    "read_commits": "storage.writer",
    "read_failures": "storage.writer",
    "stored_bytes": "storage.writer",
    "sweep_orphans": "storage.writer",
    "sweep_temporaries": "storage.writer",
    "write_failure": "storage.writer",
    "write_task": "storage.writer",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
