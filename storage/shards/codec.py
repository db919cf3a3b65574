"""The shard codec, in one place: how `storage.shards` writes every array and how readers decode it whole.

The writer stores each array as little-endian bytes, Blosc (zstd, level 3, byte shuffle) and a
CRC32C per chunk (`COMPRESSORS`: Blosc alone may decode a truncated chunk into garbage without an
error); key arrays as one shard file of inner chunks with its index at the end, itself checksummed.
`whole_array` decodes exactly that layout itself, every chunk's and the index's CRC32C checked, for a
third of zarr's CPU time on a whole-array read (zarr's per-chunk machinery costs more than the
decompression); any other layout, and any failure, goes back to zarr through `ShardReader.array`,
which raises the reader's own `StorageError` for damage. `RowTaker` reads rows of a sharded key array
decoding only the inner chunks they fall in (a version-4 cloud's window). A change of codec here
changes both sides.
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Any, Protocol

import google_crc32c
import numcodecs.blosc
import numpy as np
import numpy.typing as npt
import zarr.codecs

if TYPE_CHECKING:
    from storage.shards.group_files import GroupFiles


class ArrayReader(Protocol):
    """What the codec reads through (a `storage.shards.ShardReader`): the group's member files, and
    zarr's own read of an array for every layout and damage the fast path leaves to it."""

    files: GroupFiles

    def array(self, name: str) -> npt.NDArray[Any]: ...


COMPRESSORS = (
    zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle=zarr.codecs.BloscShuffle.shuffle),
    # A checksum per chunk: Blosc alone may decode a truncated chunk into garbage without an error.
    zarr.codecs.Crc32cCodec(),
)
"""The codecs of every array a shard group holds (after zarr's little-endian bytes codec)."""

PLAIN_BYTES = {"name": "bytes", "configuration": {"endian": "little"}}
CHECKSUM = {"name": "crc32c"}
NO_CHUNK = 2**64 - 1
"""A shard index entry of an inner chunk that was never written."""


def whole_array(reader: ArrayReader, name: str) -> npt.NDArray[Any]:
    """Array ``name`` of a verified shard, whole: decoded here when it has the layout `storage.shards`
    writes (little-endian bytes, Blosc, CRC32C; one chunk, or one shard file of inner chunks with its
    index at the end), every chunk's and the index's CRC32C checked; anything else, and any failure
    (a missing or corrupt file), is read again through `ShardReader.array`, which raises the reader's
    own `StorageError` for damage. The same values as zarr's read, for a third of its CPU time (zarr's
    per-chunk machinery costs more than the decompression itself on a whole-shard read)."""
    found = decoded_whole(reader.files, name)
    return found if found is not None else reader.array(name)


def decoded_whole(files: GroupFiles, name: str) -> npt.NDArray[Any] | None:
    """The whole array ``name`` of a group decoded here (`whole_array`'s fast path), or None when its
    layout is not the one decoded here or any member fails: the caller then reads it through zarr."""
    try:
        return _decode_whole(files, name)
    except Exception:
        return None


def _regular_array(files: GroupFiles, name: str) -> dict[str, Any] | None:
    """The zarr.json of array ``name`` when it is a plain zarr v3 array on a regular grid with the
    default "/" chunk keys (the writer's every array), else None: another layout for zarr."""
    meta: dict[str, Any] = json.loads(files.read(f"{name}/zarr.json"))
    if (
        meta.get("zarr_format") != 3
        or meta.get("node_type") != "array"
        or meta.get("storage_transformers")
        or meta["chunk_grid"].get("name") != "regular"
        or meta["chunk_key_encoding"] != {"name": "default", "configuration": {"separator": "/"}}
    ):
        return None
    return meta


def _decode_whole(files: GroupFiles, name: str) -> npt.NDArray[Any] | None:
    """The whole array ``name``, or None when its layout is not the one decoded here."""
    meta = _regular_array(files, name)
    if meta is None:
        return None
    grid = meta["chunk_grid"]
    shape = tuple(int(size) for size in meta["shape"])
    dtype = np.dtype(meta["data_type"]).newbyteorder("<")
    outer = tuple(int(size) for size in grid["configuration"]["chunk_shape"])
    if len(outer) != len(shape) or any(step < size for step, size in zip(outer, shape, strict=True)):
        return None  # more than one chunk or shard file
    if math.prod(shape) == 0:
        return np.zeros(shape, dtype=dtype)
    data = files.read(f"{name}/c/{'/'.join('0' * len(shape))}")
    codecs = meta["codecs"]
    whole = tuple(slice(0, size) for size in shape)
    if _plain(codecs):
        return _chunk(data, outer, dtype)[whole]
    if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
        return None
    config = codecs[0]["configuration"]
    inner = tuple(int(size) for size in config["chunk_shape"])
    if (
        config.get("index_location", "end") != "end"
        or config.get("index_codecs") != [PLAIN_BYTES, CHECKSUM]
        or not _plain(config["codecs"])
        or len(inner) != len(outer)
        or any(o % i for o, i in zip(outer, inner, strict=True))
    ):
        return None
    counts = tuple(o // i for o, i in zip(outer, inner, strict=True))
    index = _checked(data[-(16 * math.prod(counts) + 4) :])
    entries = np.frombuffer(index, dtype="<u8").reshape(-1, 2)
    out = np.empty(outer, dtype=dtype)
    for number, (start, size) in enumerate(entries.tolist()):
        if start == NO_CHUNK:
            return None  # zarr reads it as the fill value: leave that to zarr
        where = np.unravel_index(number, counts)
        place = tuple(slice(k * step, (k + 1) * step) for k, step in zip(where, inner, strict=True))
        target = out[place]
        if target.flags.c_contiguous:
            _chunk_into(data[start : start + size], target)  # straight into place: no copy
        else:
            target[...] = _chunk(data[start : start + size], inner, dtype)
    return out[whole]


NEAR_CHUNKS = 3
"""A take whose rows lie within this many consecutive inner chunks decodes all of them (a window
that does not wrap meets every chunk between its ends) and skips marking which ones it meets."""


class RowTaker:
    """Rows of a key array of a verified shard, decoding only the inner chunks a `take` meets.

    For the layout `storage.shards` writes a sharded key array in (one shard file of row chunks, its
    index at the end), the file is read once and each inner chunk decoded (CRC32C checked) the first
    time a take needs it: a window of a version-4 cloud costs one or two chunks, not the whole cloud.
    Any other layout, and any failure, reads the whole array (`whole_array`, and zarr through
    `ShardReader.array` for damage, which raises the reader's own `StorageError`)."""

    def __init__(self, reader: ArrayReader, name: str) -> None:
        self._reader, self._name = reader, name
        try:
            self._chunked = _open_row_chunks(reader.files, name)
        except Exception:
            self._chunked = None
        self._whole: npt.NDArray[Any] | None = None

    def take(self, rows: npt.NDArray[np.int64]) -> npt.NDArray[Any]:
        """The array's rows ``rows`` (any order, repeats allowed), stacked."""
        if self._chunked is not None:
            try:
                return self._chunked.take(rows)
            except Exception:
                self._chunked = None  # read whole below: zarr names the damage
        if self._whole is None:
            self._whole = whole_array(self._reader, self._name)
        return np.take(self._whole, rows, axis=0)


class _RowChunks:
    """One shard file of row chunks: its bytes, index and the chunks decoded so far.

    Decoded chunks stay as Blosc returned them (whole inner chunks) and a take gathers from just the
    chunks it needs: writing them into one array of the shard's size instead cost ~30x their decoding
    here, every fresh page of it faulting in on first touch."""

    def __init__(
        self, data: bytes, shape: tuple[int, ...], dtype: np.dtype[Any], inner: tuple[int, ...], count: int
    ) -> None:
        self._data, self._inner, self._dtype, self._total = data, inner, dtype, shape[0]
        self._entries = np.frombuffer(_checked(data[-(16 * count + 4) :]), dtype="<u8").reshape(-1, 2)
        if (self._entries[:, 0] == NO_CHUNK).any():
            raise ValueError("a chunk was never written")  # zarr reads it as the fill value: leave that to zarr
        self._chunks: dict[int, npt.NDArray[Any]] = {}

    def take(self, rows: npt.NDArray[np.int64]) -> npt.NDArray[Any]:
        step = self._inner[0]
        if not rows.size:
            return np.zeros((0, *self._inner[1:]), dtype=self._dtype)
        low, high = int(rows.min()), int(rows.max())
        if low < 0 or high >= self._total:
            raise IndexError(f"rows outside 0..{self._total - 1}")
        first, last = low // step, high // step
        if last - first < NEAR_CHUNKS:  # a window that does not wrap: its chunks in a row, no marks
            held = [self._decoded(number) for number in range(first, last + 1)]
            block = held[0] if len(held) == 1 else np.concatenate(held)
            return np.take(block, rows - first * step, axis=0)
        numbers = rows // step
        wanted = np.zeros(self._entries.shape[0], dtype=bool)
        wanted[numbers] = True  # marks, not np.unique: no sort of the (many) rows
        needed = np.flatnonzero(wanted)
        block = np.concatenate([self._decoded(number) for number in needed.tolist()])
        base = np.zeros(self._entries.shape[0], dtype=np.int64)
        base[needed] = np.arange(needed.size, dtype=np.int64) * step
        return np.take(block, base[numbers] + rows % step, axis=0)

    def _decoded(self, number: int) -> npt.NDArray[Any]:
        """Inner chunk ``number``, decoded (CRC32C checked) the first time it is asked for."""
        found = self._chunks.get(number)
        if found is None:
            start, size = self._entries[number].tolist()
            found = self._chunks[number] = _chunk(self._data[start : start + size], self._inner, self._dtype)
        return found


def _row_shard_layout(meta: dict[str, Any]) -> tuple[tuple[int, ...], int, tuple[int, ...]] | None:
    """(shape, shard rows, inner chunk shape) of a 2-d, non-empty array of one shard of row chunks with
    its index at the end, every codec as the writer writes it (``meta``: the zarr.json, parsed or as
    zarr's ``metadata.to_dict()``), else None: the one layout read (`RowTaker`) and written
    (`encoded_row_shard`) here."""
    codecs = list(meta.get("codecs", ()))
    if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed":
        return None
    config = codecs[0]["configuration"]
    shape = tuple(int(size) for size in meta["shape"])
    outer = tuple(int(size) for size in meta["chunk_grid"]["configuration"]["chunk_shape"])
    inner = tuple(int(size) for size in config["chunk_shape"])
    if (
        len(shape) != 2
        or outer[0] < shape[0]
        or outer[1:] != shape[1:]
        or inner[1:] != shape[1:]
        or outer[0] % inner[0]
        or config.get("index_location", "end") != "end"
        or list(config.get("index_codecs", ())) != [PLAIN_BYTES, CHECKSUM]
        or not _plain(list(config["codecs"]))
        or math.prod(shape) == 0
    ):
        return None
    return shape, outer[0], inner


def _open_row_chunks(files: GroupFiles, name: str) -> _RowChunks | None:
    """The row-chunked shard file of array ``name``, or None for another layout."""
    meta = _regular_array(files, name)
    layout = _row_shard_layout(meta) if meta is not None else None
    if meta is None or layout is None:
        return None
    shape, shard_rows, inner = layout
    dtype = np.dtype(meta["data_type"]).newbyteorder("<")
    data = files.read(f"{name}/c/0/0")
    return _RowChunks(data, shape, dtype, inner, shard_rows // inner[0])


def encoded_row_shard(data: npt.NDArray[Any], meta: dict[str, Any]) -> bytes | None:
    """The shard file zarr writes for ``data`` (rows x columns) as the one shard of an array whose
    zarr.json is ``meta``: its inner chunks of the rows recorded there (the last padded with the fill
    value, zeros), each little-endian bytes, Blosc as recorded and a CRC32C, in row order, then the
    (offset, size) index and its CRC32C. None for any other layout (the caller lets zarr write).
    ``meta`` may be zarr's ``metadata.to_dict()`` (tuples) or the parsed file (lists).

    Why not zarr: its codec pipeline costs ~0.25 ms an inner chunk beyond the compression itself,
    which for a version-4 ``points_keys`` of hundreds of 2,048-row chunks doubled a task's write.
    tests/storage/test_shard_encoding.py checks these bytes against zarr's own."""
    layout = _row_shard_layout(meta)
    if layout is None or meta.get("fill_value") != 0 or data.shape != layout[0]:
        return None
    _, shard_rows, inner = layout
    inner_rows = inner[0]
    blosc = meta["codecs"][0]["configuration"]["codecs"][1]["configuration"]
    if blosc.get("shuffle") not in BLOSC_SHUFFLES or int(blosc.get("typesize", 0)) != data.dtype.itemsize:
        return None
    compressor = numcodecs.blosc.Blosc(
        cname=blosc["cname"],
        clevel=int(blosc["clevel"]),
        shuffle=BLOSC_SHUFFLES[blosc["shuffle"]],
        blocksize=int(blosc.get("blocksize", 0)),
        typesize=data.dtype.itemsize,
    )
    padded = np.zeros((shard_rows, data.shape[1]), dtype=data.dtype.newbyteorder("<"))
    padded[: data.shape[0]] = data
    parts: list[bytes] = []
    index = np.empty((shard_rows // inner_rows, 2), dtype="<u8")
    offset = 0
    for number, start in enumerate(range(0, shard_rows, inner_rows)):
        body = compressor.encode(padded[start : start + inner_rows])
        parts.append(body)
        parts.append(np.uint32(google_crc32c.value(body)).astype("<u4").tobytes())
        index[number] = (offset, len(body) + 4)
        offset += len(body) + 4
    table = index.tobytes()
    return b"".join([*parts, table, np.uint32(google_crc32c.value(table)).astype("<u4").tobytes()])


BLOSC_SHUFFLES = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}
"""numcodecs' number of each Blosc shuffle zarr names in a zarr.json."""


WRITTEN_CODECS = ("bytes", *(codec.to_dict()["name"] for codec in COMPRESSORS))
"""The codec names of a chunk as the writer stores it, in order (``bytes``, ``blosc``, ``crc32c``)."""


def _plain(codecs: list[dict[str, Any]]) -> bool:
    """A chunk codec list as the writer writes it: little-endian bytes (zarr names no endianness for a
    one-byte type), then `COMPRESSORS`."""
    names = tuple(codec.get("name") for codec in codecs)
    return names == WRITTEN_CODECS and codecs[0] in (PLAIN_BYTES, {"name": "bytes"})


def _checked(data: bytes) -> bytes:
    """The bytes before a CRC32C suffix, which must match them."""
    body = data[:-4]
    if len(data) < 4 or np.uint32(google_crc32c.value(body)).tobytes() != data[-4:]:
        raise ValueError("checksum mismatch")
    return body


def _chunk_into(data: bytes, target: npt.NDArray[Any]) -> None:
    """One Blosc chunk with its CRC32C decoded into ``target`` (C-contiguous), which it must fill
    exactly: its size is read from the Blosc header (bytes 4 to 8, little-endian) first."""
    body = _checked(data)
    if len(body) < 16 or int.from_bytes(body[4:8], "little") != target.nbytes:
        raise ValueError("chunk of the wrong size")
    numcodecs.blosc.decompress(body, target)


def _chunk(data: bytes, shape: tuple[int, ...], dtype: np.dtype[Any]) -> npt.NDArray[Any]:
    """One Blosc chunk with its CRC32C, as an array of ``shape``."""
    decoded = numcodecs.blosc.decompress(_checked(data))
    if len(decoded) != math.prod(shape) * dtype.itemsize:
        raise ValueError("chunk of the wrong size")
    return np.frombuffer(decoded, dtype=dtype).reshape(shape)
