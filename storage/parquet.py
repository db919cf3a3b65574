"""Parquet in and out of a dataset: always single-threaded, and a damaged file is named.

pyarrow's threaded reader (``use_threads=True``, its default) leaves its thread pool running into
interpreter shutdown; with pyarrow 26 a short script that opened a dataset then aborted with
SIGABRT ("terminate called without an active exception") in most runs. An index is a few MB at
most, so one thread costs nothing noticeable. Every Parquet read in `storage` goes through here.
"""

from __future__ import annotations

import io

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.index import INDEX_SCHEMA
from storage.location import Location, damaged, first_line


def read_parquet(location: Location, relative: str, schema: pa.Schema | None = INDEX_SCHEMA) -> pa.Table:
    """The table at ``relative`` read on the calling thread; `DamagedFile` when it is missing or bad.

    ``schema=None`` reads the columns as stored (`storage.validate` compares them itself).
    """
    try:
        data = location.read_bytes(relative)
    except FileNotFoundError:
        raise damaged(location.url, relative, "missing") from None
    try:
        return pq.read_table(io.BytesIO(data), schema=schema, use_threads=False, pre_buffer=False)
    except (pa.ArrowException, ValueError, TypeError, OSError) as exc:
        raise damaged(location.url, relative, f"unreadable Parquet ({first_line(exc)})") from None


def parquet_bytes(table: pa.Table) -> bytes:
    """A whole Parquet file (zstd) in memory, to be published with one atomic write."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return bytes(sink.getvalue().to_pybytes())
