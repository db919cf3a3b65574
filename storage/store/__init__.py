"""Where a dataset lives: a local path or any fsspec URL (`Location`), what a store that cannot be
reached or refuses says (`check_store`, `storage_failure`), and Parquet in and out of it.

The ground floor of `storage`: it imports nothing of `storage`. Its modules: ``location`` (the
`Location` and its errors), ``errors`` (telling a store's failure from a damaged file), ``parquet``.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.store.errors import check_store, is_store_failure, is_transient, storage_failure, store_errors
    from storage.store.location import (
        REPAIR_COMMAND,
        RERUN_FIX,
        DamagedFile,
        Location,
        StorageError,
        StoreUnreachable,
        is_s3,
        open_location,
    )
    from storage.store.parquet import parquet_bytes, read_index_table, read_parquet

__all__ = [
    "REPAIR_COMMAND",
    "RERUN_FIX",
    "DamagedFile",
    "Location",
    "StorageError",
    "StoreUnreachable",
    "check_store",
    "is_s3",
    "is_store_failure",
    "is_transient",
    "open_location",
    "parquet_bytes",
    "read_index_table",
    "read_parquet",
    "storage_failure",
    "store_errors",
]

_HOMES = {
    "DamagedFile": "storage.store.location",
    "Location": "storage.store.location",
    "StorageError": "storage.store.location",
    "StoreUnreachable": "storage.store.location",
    "is_s3": "storage.store.location",
    "open_location": "storage.store.location",
    "RERUN_FIX": "storage.store.location",
    "REPAIR_COMMAND": "storage.store.location",
    "check_store": "storage.store.errors",
    "is_store_failure": "storage.store.errors",
    "is_transient": "storage.store.errors",
    "storage_failure": "storage.store.errors",
    "store_errors": "storage.store.errors",
    "parquet_bytes": "storage.store.parquet",
    "read_index_table": "storage.store.parquet",
    "read_parquet": "storage.store.parquet",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
