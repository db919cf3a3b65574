"""The shard files `storage.shards` writes itself are zarr's own bytes.

`storage.shards.encoded_row_shard` encodes a sharded key array without zarr's codec pipeline; the
truth here is zarr writing the same array through ``array[...] = data``: every file must be
byte-identical, so a dataset written either way is the same dataset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr
from support import storage as fx

from schemas.shard import array_names
from storage import open_location
from storage.shards import COMPRESSORS, POINT_CHUNK_ROWS, WRITE_EVERY_CHUNK, encoded_row_shard, write_shard_group


def zarr_written(folder: Path, data: np.ndarray, rows: int) -> bytes:
    """The shard file zarr itself writes for ``data`` in ``rows``-row inner chunks."""
    shard_rows = -(-data.shape[0] // rows) * rows
    group = zarr.open_group(str(folder), mode="w")
    array = group.create_array(
        "x",
        shape=data.shape,
        dtype=data.dtype,
        chunks=(rows, 3),
        shards=(shard_rows, 3),
        compressors=COMPRESSORS,
        config=WRITE_EVERY_CHUNK,
    )
    array[...] = data
    return (folder / "x" / "c" / "0" / "0").read_bytes()


@pytest.mark.parametrize("count", [1, 2047, 2048, 2049, 30_000])
@pytest.mark.parametrize("rows", [POINT_CHUNK_ROWS, 32_768])
def test_a_row_shard_is_zarrs_bytes(tmp_path: Path, count: int, rows: int) -> None:
    """Random keys (a version-4 cloud's order) and sorted ones, a partial last chunk, one chunk, many."""
    rng = np.random.default_rng(count)
    for kind, data in (
        ("random", rng.integers(-300, 300, size=(count, 3)).astype(np.int16)),
        ("sorted", np.sort(rng.integers(0, 64, size=(count, 3)).astype(np.int16), axis=0)),
    ):
        truth = zarr_written(tmp_path / kind, data, rows)
        meta = zarr.open_array(str(tmp_path / kind / "x"), mode="r").metadata.to_dict()
        assert encoded_row_shard(data, meta) == truth, kind


def test_another_layout_is_left_to_zarr(tmp_path: Path) -> None:
    data = np.ones((100, 3), dtype=np.int16)
    zarr_written(tmp_path, data, 64)
    meta = zarr.open_array(str(tmp_path / "x"), mode="r").metadata.to_dict()
    assert encoded_row_shard(data, meta) is not None
    assert encoded_row_shard(data[:, :2], meta) is None  # not the recorded width
    assert encoded_row_shard(np.ones((100, 3), dtype=np.int32), meta) is None  # not the recorded type size
    assert encoded_row_shard(np.ones((200, 3), dtype=np.int16), meta) is None  # more rows than the shard
    other = dict(meta, fill_value=7)
    assert encoded_row_shard(data, other) is None  # padding would not be zeros
    plain = dict(meta, codecs=[{"name": "bytes", "configuration": {"endian": "little"}}])
    assert encoded_row_shard(data, plain) is None  # not sharded


@pytest.mark.parametrize("schema_version", [3, 4])
def test_a_task_group_is_zarrs_files(tmp_path: Path, schema_version: int) -> None:
    """A whole task's shard group, written by `write_shard_group` and by zarr alone: the same files."""
    payload = fx.payloads(schema_version)[0]
    attributes = payload.attributes
    ours = tmp_path / "ours"
    write_shard_group(open_location(str(ours)), "g", attributes, payload.arrays)
    reference = zarr.open_group(str(tmp_path / "zarr" / "g"), mode="w")
    for name in array_names(schema_version):
        source = zarr.open_array(str(ours / "g" / name), mode="r")
        array = reference.create_array(
            name,
            shape=source.shape,
            dtype=source.dtype,
            chunks=source.chunks,
            shards=source.shards,
            compressors=COMPRESSORS,
            config=WRITE_EVERY_CHUNK,
        )
        if source.size:
            array[...] = payload.arrays[name]
    reference.attrs.put(attributes.model_dump(mode="json"))
    files = sorted(p.relative_to(ours / "g") for p in (ours / "g").rglob("*") if p.is_file())
    assert files == sorted(
        p.relative_to(tmp_path / "zarr" / "g") for p in (tmp_path / "zarr" / "g").rglob("*") if p.is_file()
    )
    sharded = [f for f in files if f.parts[-3:] == ("c", "0", "0") and (ours / "g" / f.parts[0] / "zarr.json").exists()]
    assert any("points_keys" in f.parts for f in sharded)
    for name in files:
        assert (ours / "g" / name).read_bytes() == (tmp_path / "zarr" / "g" / name).read_bytes(), name
