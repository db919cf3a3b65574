"""Parquet in and out of a dataset: always single-threaded, and a damaged file is named.

pyarrow's threaded reader (``use_threads=True``, its default) leaves its thread pool running into
interpreter shutdown; with pyarrow 26 a short script that opened a dataset then aborted with
SIGABRT ("terminate called without an active exception") in most runs. ``pq.read_table`` starts a
pool even with ``use_threads=False`` (it scans through the dataset API), which still aborted about
1 run in 20 on a loaded machine; `pq.ParquetFile.read` on a buffer starts none. An index is a few MB
at most, so one thread costs nothing noticeable. Every Parquet read in `storage` goes through here.
"""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.index import INDEX_SCHEMAS, index_schema_version
from storage.store.location import Location, damaged, first_line


def read_parquet(location: Location, relative: str) -> pa.Table:
    """The table at ``relative`` as stored, read on the calling thread; `DamagedFile` when it is
    missing or bad (`storage.validate` compares the columns itself)."""
    try:
        data = location.read_bytes(relative)
    except FileNotFoundError:
        raise damaged(location.url, relative, "missing") from None
    try:
        return pq.ParquetFile(pa.BufferReader(data), pre_buffer=False).read(use_threads=False)
    except (pa.ArrowException, ValueError, TypeError, OSError) as exc:
        raise damaged(location.url, relative, f"unreadable Parquet ({first_line(exc)})") from None


def read_index_table(location: Location, relative: str) -> pa.Table:
    """An index file (merged or a fragment): its columns must be those of a layout version this
    code reads (`schemas.index.INDEX_SCHEMAS`); `DamagedFile` otherwise."""
    table = read_parquet(location, relative)
    version = index_schema_version(table.schema)
    if version is None:
        raise damaged(location.url, relative, "index columns match no known schema version")
    schema = INDEX_SCHEMAS[version]
    if table.schema.equals(schema, check_metadata=False):
        return table  # a cast of equal columns costs ~50 us each: ~2 ms a fragment
    try:
        return table.cast(schema)
    except (pa.ArrowException, ValueError) as exc:  # nulls in a column that may hold none
        raise damaged(location.url, relative, f"unreadable index columns ({first_line(exc)})") from None


def parquet_bytes(table: pa.Table) -> bytes:
    """A whole Parquet file (zstd) in memory, to be published with one atomic write."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return bytes(sink.getvalue().to_pybytes())
