"""A task's shard: one Zarr v3 group of its arrays, written once and read back in whole blocks.

``groups`` writes a shard group and reads it (`ShardReader`, verified whole before its first read),
``codec`` is how every array is encoded and decoded (one place for the writer and the readers), and
``group_files`` where a group's members live (a folder of files, layouts 1-4, or one ZIP, a span of a
pack among them). It imports only `storage.store`.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
    from storage.shards.codec import COMPRESSORS, RowTaker, encoded_row_shard, whole_array
    from storage.shards.group_files import local_files, zip_bytes, zip_entries
    from storage.shards.groups import (
        KEY_CHUNK_ROWS,
        POINT_CHUNK_ROWS,
        WRITE_EVERY_CHUNK,
        ShardReader,
        write_shard_group,
    )

__all__ = [
    "COMPRESSORS",
    "KEY_CHUNK_ROWS",
    "POINT_CHUNK_ROWS",
    "WRITE_EVERY_CHUNK",
    "RowTaker",
    "ShardReader",
    "encoded_row_shard",
    "local_files",
    "whole_array",
    "write_shard_group",
    "zip_bytes",
    "zip_entries",
]

_HOMES = {
    "KEY_CHUNK_ROWS": "storage.shards.groups",
    "POINT_CHUNK_ROWS": "storage.shards.groups",
    "WRITE_EVERY_CHUNK": "storage.shards.groups",
    "ShardReader": "storage.shards.groups",
    "write_shard_group": "storage.shards.groups",
    "COMPRESSORS": "storage.shards.codec",
    "RowTaker": "storage.shards.codec",
    "encoded_row_shard": "storage.shards.codec",
    "whole_array": "storage.shards.codec",
    "local_files": "storage.shards.group_files",
    "zip_bytes": "storage.shards.group_files",
    "zip_entries": "storage.shards.group_files",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
