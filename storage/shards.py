"""Zarr v3 shard groups: write a task's arrays once each, read them back in whole blocks.

Small arrays (masks, offsets) are one chunk. Key arrays are chunked in blocks of `KEY_CHUNK_ROWS`
rows inside one sharded file, so a reader can fetch one sample's rows without the whole array.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import zarr
import zarr.codecs
from zarr.storage import FsspecStore, LocalStore

from schemas.shard import ShardAttributes, array_names
from storage.location import Location

KEY_CHUNK_ROWS = 32_768
COMPRESSORS = (
    zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle=zarr.codecs.BloscShuffle.shuffle),
    # A checksum per chunk: Blosc alone may decode a truncated chunk into garbage without an error.
    zarr.codecs.Crc32cCodec(),
)


def zarr_store(location: Location, relative: str, read_only: bool) -> Any:
    if location.is_local:
        return LocalStore(location.path(relative), read_only=read_only)
    return FsspecStore.from_url(
        location.url_of(relative), storage_options=location.storage_options or None, read_only=read_only
    )


def write_shard_group(
    location: Location, relative: str, attributes: ShardAttributes, arrays: dict[str, npt.NDArray[Any]]
) -> None:
    """Write every array of a shard group once (the group is new: one attempt, one path)."""
    missing = sorted(set(array_names()) - set(arrays))
    if missing:
        raise ValueError(f"shard arrays missing: {missing}")
    group = zarr.open_group(zarr_store(location, relative, read_only=False), mode="w")
    for name in sorted(arrays):
        data = np.ascontiguousarray(arrays[name])
        if name.endswith("_keys") and data.shape[0] > KEY_CHUNK_ROWS:
            rows = KEY_CHUNK_ROWS
            shard_rows = -(-data.shape[0] // rows) * rows
            array = group.create_array(
                name,
                shape=data.shape,
                dtype=data.dtype,
                chunks=(rows, 3),
                shards=(shard_rows, 3),
                compressors=COMPRESSORS,
            )
        else:
            chunks = tuple(max(1, s) for s in data.shape)
            array = group.create_array(name, shape=data.shape, dtype=data.dtype, chunks=chunks, compressors=COMPRESSORS)
        if data.size:
            array[...] = data
    group.attrs.put(attributes.model_dump(mode="json"))


class ShardReader:
    """Read access to one committed shard group; whole arrays are cached after first use."""

    def __init__(self, location: Location, relative: str) -> None:
        self.location = location
        self.relative = relative
        self._group = zarr.open_group(zarr_store(location, relative, read_only=True), mode="r")
        self._cache: dict[str, npt.NDArray[Any]] = {}
        self._nodes: dict[str, zarr.Array[Any]] = {}
        self.attributes = ShardAttributes.model_validate(dict(self._group.attrs))

    def _array(self, name: str) -> zarr.Array[Any]:
        """The array node, opened once (each open is a metadata read)."""
        node = self._nodes.get(name)
        if node is None:
            found = self._group[name]
            if not isinstance(found, zarr.Array):
                raise KeyError(f"{self.relative}: {name} is not an array")
            node = self._nodes[name] = found
        return node

    def array(self, name: str) -> npt.NDArray[Any]:
        """A whole array (cached)."""
        if name not in self._cache:
            self._cache[name] = np.asarray(self._array(name)[...])
        return self._cache[name]

    def array_names(self) -> list[str]:
        return sorted(self._group.array_keys())

    def array_shape(self, name: str) -> tuple[int, ...]:
        return tuple(self._array(name).shape)

    def incomplete_arrays(self, names: list[str]) -> list[str]:
        """The arrays with fewer stored objects (chunk or shard files) than their grid needs.

        One listing of the group instead of one per array. A lost inner chunk of a shard file
        cannot hide here: the file is written whole, and a damaged one fails its CRC32C on read.
        """
        root = self.location.path(self.relative).rstrip("/")
        stored: dict[str, int] = {}
        for path in self.location.fs.find(root):
            parts = str(path)[len(root) :].strip("/").split("/")
            if len(parts) > 2 and parts[1] == "c":
                stored[parts[0]] = stored.get(parts[0], 0) + 1
        incomplete = []
        for name in names:
            array = self._array(name)
            if array.size == 0:
                continue
            grid = array.shards or array.chunks
            needed = int(np.prod([-(-size // step) for size, step in zip(array.shape, grid, strict=True)]))
            if stored.get(name, 0) < needed:
                incomplete.append(name)
        return sorted(incomplete)

    def array_dtype(self, name: str) -> np.dtype[Any]:
        return np.dtype(self._array(name).dtype)

    def key_set(self, name: str, row: int) -> npt.NDArray[np.int16]:
        """Rows ``offsets[row]:offsets[row + 1]`` of ``<name>_keys``."""
        offsets = self.array(f"{name}_offsets")
        return self.array(f"{name}_keys")[offsets[row] : offsets[row + 1]]
