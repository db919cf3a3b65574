"""The digest's column hasher, which walks a column a slice at a time, feeds exactly the bytes of
hashing the whole column as one Python list: across chunk and slice boundaries, with empty chunks,
nulls, strings, floats and list values."""

from __future__ import annotations

import hashlib

import pyarrow as pa
import pytest

from storage.readers import digest


@pytest.mark.parametrize(
    "chunks",
    [
        [[1, 2, 3, 4, 5], [], [6, None, 8]],
        [["a", "b'c"], ['d"e', None, "f"], [], ["g"]],
        [[0.1, 2.5e-300], [float("inf"), -0.0, None]],
        [[[1, 2], [], None], [[3]]],
        [[], []],
    ],
)
def test_sliced_column_hash_is_the_whole_list_hash(chunks: list[list[object]], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(digest, "COLUMN_SLICE_ROWS", 2)
    column = pa.chunked_array(chunks, type=pa.chunked_array(chunks).type if any(chunks) else pa.int64())
    whole, sliced = hashlib.sha256(), hashlib.sha256()
    digest._feed(whole, "index/x", column.to_pylist())
    digest._feed_column(sliced, "index/x", column)
    assert sliced.hexdigest() == whole.hexdigest()
