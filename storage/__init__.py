"""Reading and writing datasets on any fsspec URL: Zarr v3 shards, a Parquet index, commit records.

This module is storage's public face: every name below is imported from its layer when first used,
so ``import storage`` stays light. The layers are sub-packages, each importing only those before it
in this list (`tests/storage/test_layers.py` holds them to it):

1. `storage.store`: where a dataset lives (`Location`, any fsspec URL), store errors, Parquet IO;
2. `storage.samples`: the sample contract and its mathematics without a store (the batch, the field
   registry and the one assembler, resampling, splits, covers, gains, grids, label judges);
3. `storage.shards`: a task's Zarr v3 shard group, its codec and its files;
4. `storage.dataset`: the commit protocol, the manifest and index, ``dataset.json``, packing;
5. `storage.readers`: `open_dataset` and `load_memory` (numpy), and the PyTorch readers behind
   `storage.torch` (`OSVPDataset`) and `storage.stream` (`ShardStream`);
6. `storage.checks`: `validate` and repair;
7. `storage.export`: the authors' file layouts.

Code outside storage imports this module, a layer's face or `storage.torch`, `storage.stream`,
never a module inside a layer. Depends on numpy, zarr, pyarrow, fsspec and `schemas` only: a
training package needs nothing else (`storage.torch` and `storage.stream` add PyTorch, imported
only when those modules are).
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.checks import SAMPLED_ROWS_PER_SHARD, Validation, validate, validate_dataset
    from storage.dataset import (
        Mend,
        Problem,
        ShardPayload,
        committed_tasks,
        existing_info,
        finalise,
        holds_dataset,
        init_dataset,
        load_index,
        read_commit,
        read_commits,
        read_failures,
        read_info,
        stored_bytes,
        sweep_orphans,
        sweep_temporaries,
        write_failure,
        write_task,
    )
    from storage.export import export_air
    from storage.readers import Dataset, LabelAmbiguity, NextView, dataset_digest, open_dataset
    from storage.samples import covers_universe, nearest_cover, undominated, universe_rows
    from storage.shards import ShardReader
    from storage.store import (
        DamagedFile,
        Location,
        StorageError,
        StoreUnreachable,
        check_store,
        is_s3,
        is_store_failure,
        is_transient,
        open_location,
        storage_failure,
        store_errors,
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
    "dataset_digest",
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
    "SAMPLED_ROWS_PER_SHARD": "storage.checks",
    "Validation": "storage.checks",
    "validate": "storage.checks",
    "validate_dataset": "storage.checks",
    "Mend": "storage.dataset",
    "Problem": "storage.dataset",
    "ShardPayload": "storage.dataset",
    "committed_tasks": "storage.dataset",
    "existing_info": "storage.dataset",
    "finalise": "storage.dataset",
    "holds_dataset": "storage.dataset",
    "init_dataset": "storage.dataset",
    "load_index": "storage.dataset",
    "read_commit": "storage.dataset",
    "read_commits": "storage.dataset",
    "read_failures": "storage.dataset",
    "read_info": "storage.dataset",
    "stored_bytes": "storage.dataset",
    "sweep_orphans": "storage.dataset",
    "sweep_temporaries": "storage.dataset",
    "write_failure": "storage.dataset",
    "write_task": "storage.dataset",
    "export_air": "storage.export",
    "Dataset": "storage.readers",
    "LabelAmbiguity": "storage.readers",
    "NextView": "storage.readers",
    "open_dataset": "storage.readers",
    "dataset_digest": "storage.readers",
    "covers_universe": "storage.samples",
    "nearest_cover": "storage.samples",
    "undominated": "storage.samples",
    "universe_rows": "storage.samples",
    "ShardReader": "storage.shards",
    "DamagedFile": "storage.store",
    "Location": "storage.store",
    "StorageError": "storage.store",
    "StoreUnreachable": "storage.store",
    "check_store": "storage.store",
    "is_s3": "storage.store",
    "is_store_failure": "storage.store",
    "is_transient": "storage.store",
    "open_location": "storage.store",
    "storage_failure": "storage.store",
    "store_errors": "storage.store",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
