"""Zarr v3 shard groups: write a task's arrays once each, read them back in whole blocks.

Small arrays (masks, offsets) are one chunk. Key arrays are chunked in blocks of `KEY_CHUNK_ROWS`
rows inside one sharded file, so a reader can fetch one sample's rows without the whole array. A
version-4 ``points_keys`` (each cloud in `schemas.shard.point_order`) is chunked in blocks of
`POINT_CHUNK_ROWS`, so that a window of a cloud's stored order decodes only the chunks it meets.
"""

from __future__ import annotations

import json
import math
import os
import posixpath
from collections.abc import Iterable
from typing import Any

import numpy as np
import numpy.typing as npt
import zarr
import zarr.codecs
from zarr.core.array_spec import ArrayConfigParams
from zarr.storage import FsspecStore, LocalStore

from schemas.shard import ShardAttributes, array_names, ordered_points
from storage.codec import COMPRESSORS, RowTaker, decoded_whole, encoded_row_shard
from storage.location import Location, damaged, first_line, is_temporary
from storage.store_errors import is_store_failure, storage_failure

KEY_CHUNK_ROWS = 32_768
POINT_CHUNK_ROWS = 2_048
"""Inner chunk rows of a version-4 ``points_keys``. A window of N consecutive rows meets
ceil(N / C) or one more chunks of C rows, about N + C rows decoded on average: C = 2,048 makes the
default 2,048-point window meet two chunks (4,096 rows, against ~17,700 in a whole cloud of a POCO
dataset), 1,024 and 4,096 points one to three. Smaller chunks would decode fewer rows but pay
Blosc's and the CRC32C's per-chunk cost and compress worse (12 KB raw a chunk here)."""
WRITE_EVERY_CHUNK: ArrayConfigParams = {"write_empty_chunks": True}
"""zarr skips a chunk that holds only the fill value (zeros) and reads it back as zeros; a reader
could not tell it from a lost file. Every chunk is written, so a missing chunk file always means
damage (a task whose every label is empty stores all-zero covers)."""


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
    missing = sorted(set(array_names(attributes.schema_version)) - set(arrays))
    if missing:
        raise ValueError(f"shard arrays missing: {missing}")
    group = zarr.open_group(zarr_store(location, relative, read_only=False), mode="w")
    for name in sorted(arrays):
        data = np.ascontiguousarray(arrays[name])
        rows = KEY_CHUNK_ROWS
        if ordered_points(attributes.schema_version, name.removesuffix("_keys")) and name.endswith("_keys"):
            rows = POINT_CHUNK_ROWS
        if name.endswith("_keys") and data.shape[0] > rows:
            shard_rows = -(-data.shape[0] // rows) * rows
            array = group.create_array(
                name,
                shape=data.shape,
                dtype=data.dtype,
                chunks=(rows, 3),
                shards=(shard_rows, 3),
                compressors=COMPRESSORS,
                config=WRITE_EVERY_CHUNK,
            )
        else:
            chunks = tuple(max(1, s) for s in data.shape)
            array = group.create_array(
                name,
                shape=data.shape,
                dtype=data.dtype,
                chunks=chunks,
                compressors=COMPRESSORS,
                config=WRITE_EVERY_CHUNK,
            )
        if data.size and not _wrote_row_shard(location, f"{relative}/{name}", data, array):
            array[...] = data
    group.attrs.put(attributes.model_dump(mode="json"))


def _wrote_row_shard(location: Location, relative: str, data: npt.NDArray[Any], array: zarr.Array[Any]) -> bool:
    """Write a sharded key array's one shard file as zarr would (`storage.codec.encoded_row_shard`,
    the same bytes for a fraction of zarr's CPU); False, writing nothing, for any other layout."""
    blob = encoded_row_shard(data, dict(array.metadata.to_dict()))
    if blob is None:
        return False
    target = location.path(f"{relative}/c/0/0")
    location.fs.makedirs(posixpath.dirname(target), exist_ok=True)
    location.fs.pipe_file(target, blob)
    return True


DAMAGE = (OSError, ValueError, KeyError, TypeError, IndexError, RuntimeError, EOFError)
"""What zarr, numcodecs and the stores raise on a missing, truncated or corrupt file (a CRC32C
mismatch is a ValueError, a missing member a KeyError, bad metadata a JSONDecodeError or a
validation error, a short Blosc frame a RuntimeError)."""


def local_files(top: str) -> list[str]:
    """Paths, relative to ``top`` and sorted, of the non-empty files below local folder ``top`` (none
    when it is missing): what fsspec's ``find`` lists there, without its cost (about 3 ms for a shard
    of 30 files, a tenth of that here), which a streaming reader pays for every shard."""
    found: list[str] = []
    folders = [("", top)]
    while folders:
        prefix, folder = folders.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for entry in entries:
            try:
                if entry.is_dir():
                    folders.append((f"{prefix}{entry.name}/", entry.path))
                elif entry.stat().st_size:
                    found.append(f"{prefix}{entry.name}")
            except FileNotFoundError:
                continue  # gone since the listing (a temporary file renamed into place)
    return sorted(found)


class ShardReader:
    """Read access to one committed shard group; whole arrays are cached after first use.

    Every failure to read the group is a `DamagedFile` naming the shard (path relative to the
    dataset) and the fix; `verify` (run on opening unless ``verify=False``) also finds what zarr
    would otherwise hide: a missing or emptied chunk file reads back as the fill value (zeros),
    silently. `storage.validate` opens without it and reports each finding as a line instead.
    """

    def __init__(self, location: Location, relative: str, verify: bool = True) -> None:
        self.location = location
        self.relative = relative
        self._cache: dict[str, npt.NDArray[Any]] = {}
        self._takers: dict[str, RowTaker] = {}
        self._nodes: dict[str, zarr.Array[Any]] = {}
        self._files: set[str] | None = None
        self._zarr_group: zarr.Group | None = None
        found = self._plain_attributes()
        if found is None:
            try:
                found = ShardAttributes.model_validate(dict(self._group.attrs))
            except DAMAGE as exc:
                raise self._damage(f"unreadable group metadata zarr.json ({first_line(exc)})", cause=exc) from exc
        self.attributes = found
        if verify:
            self.verify()

    @property
    def _group(self) -> zarr.Group:
        """The zarr group, opened on first use: a reader that only needs the attributes and whole
        arrays (`storage.codec.whole_array`) never opens it (about 1 ms a shard, most of it zarr waking
        its event loop thread)."""
        if self._zarr_group is None:
            try:
                self._zarr_group = zarr.open_group(zarr_store(self.location, self.relative, read_only=True), mode="r")
            except FileNotFoundError as exc:
                raise self._damage("the shard group is missing") from exc
            except DAMAGE as exc:
                raise self._damage(f"unreadable group metadata zarr.json ({first_line(exc)})", cause=exc) from exc
        return self._zarr_group

    def _plain_attributes(self) -> ShardAttributes | None:
        """The shard's attributes read from its group ``zarr.json`` directly, when that file is a plain
        Zarr v3 group as the writer writes it (nothing but its attributes) and they validate; else None,
        and zarr opens the group, raising the reader's usual errors for what is wrong with it."""
        try:
            meta = json.loads(self.location.read_bytes(f"{self.relative}/zarr.json"))
            if (
                not isinstance(meta, dict)
                or set(meta) - {"zarr_format", "node_type", "attributes"}
                or meta.get("zarr_format") != 3
                or meta.get("node_type") != "group"
                or not isinstance(meta.get("attributes"), dict)
            ):
                return None
            return ShardAttributes.model_validate(meta["attributes"])
        except Exception:
            return None

    def _damage(self, problem: str, relative: str | None = None, cause: BaseException | None = None) -> Exception:
        """`DamagedFile` for the file, unless ``cause`` is a failure of the store itself (unreachable,
        refused): then the store's one line, so nobody re-runs a sound task for a network error."""
        if cause is not None and is_store_failure(cause):
            return storage_failure(self.location.url, cause)
        return damaged(self.location.url, relative or self.relative, problem, rerun_task=True)

    def _array(self, name: str) -> zarr.Array[Any]:
        """The array node, opened once (each open is a metadata read)."""
        node = self._nodes.get(name)
        if node is None:
            try:
                found = self._group[name]
            except KeyError:
                raise self._damage(f"array {name} is missing") from None
            except DAMAGE as exc:
                raise self._damage(f"unreadable metadata {name}/zarr.json ({first_line(exc)})", cause=exc) from exc
            if not isinstance(found, zarr.Array):
                raise self._damage(f"{name} is not an array")
            node = self._nodes[name] = found
        return node

    def array(self, name: str) -> npt.NDArray[Any]:
        """A whole array (cached): decoded by `storage.codec` where it has the layout written here (zarr's
        per-chunk machinery costs several times the decompression of a version-4 ``points_keys``'
        hundreds of small chunks), through zarr otherwise and for every failure, which names the damage."""
        if name not in self._cache:
            found = decoded_whole(self.location, f"{self.relative}/{name}")
            if found is not None:
                # writable, as zarr's: a one-chunk array is a view of the decoded bytes
                self._cache[name] = found if found.flags.writeable else found.copy()
                return self._cache[name]
            node = self._array(name)
            try:
                self._cache[name] = np.asarray(node[...])
            except DAMAGE as exc:
                problem = f"unreadable chunk data ({first_line(exc)}); the shard is truncated or corrupt"
                raise self._damage(problem, f"{self.relative}/{name}", cause=exc) from exc
        return self._cache[name]

    def array_names(self) -> list[str]:
        try:
            return sorted(self._group.array_keys())
        except DAMAGE as exc:
            raise self._damage(f"unreadable array metadata ({first_line(exc)})", cause=exc) from exc

    def array_shape(self, name: str) -> tuple[int, ...]:
        return tuple(self._array(name).shape)

    def verify(self) -> None:
        """Raise `DamagedFile` unless every array of the layout is there with all its chunk files.

        One listing of the group plus each array's metadata (which reading needs anyway): what a
        reader pays once per shard, so that a lost file is an error rather than zeroed points.
        """
        names = array_names(self.attributes.schema_version)
        missing = self.missing_arrays(names)
        if missing:
            raise self._damage(f"arrays missing {missing}; the shard is truncated")
        short = [f"{name} ({stored} of {needed} chunk files)" for name, stored, needed in self._chunk_counts(names)]
        if short:
            raise self._damage(f"missing chunk files: {', '.join(short)}; the shard is truncated")

    def missing_arrays(self, names: list[str]) -> list[str]:
        """The arrays among ``names`` whose metadata file is not in the group (from the listing)."""
        stored = self._listing()
        return sorted(name for name in names if f"{name}/zarr.json" not in stored)

    def incomplete_arrays(self, names: list[str]) -> list[str]:
        """The arrays with fewer stored objects (chunk or shard files) than their grid needs.

        One listing of the group instead of one per array; an empty file counts as missing (zarr
        reads it as the fill value). A lost inner chunk of a shard file cannot hide here: the file
        is written whole, and a damaged one fails its CRC32C on read.
        """
        return sorted(name for name, _, _ in self._chunk_counts(names))

    def _chunk_counts(self, names: list[str]) -> list[tuple[str, int, int]]:
        """(name, stored, needed) for each array of ``names`` with fewer chunk files than needed."""
        stored: dict[str, int] = {}
        for path in self._listing():
            parts = path.split("/")
            if len(parts) > 2 and parts[1] == "c":
                stored[parts[0]] = stored.get(parts[0], 0) + 1
        short = []
        for name in names:
            needed = self._chunks_needed(name)
            if stored.get(name, 0) < needed:
                short.append((name, stored.get(name, 0), needed))
        return short

    def _chunks_needed(self, name: str) -> int:
        """Cells of the array's chunk grid (shards, for a sharded array): one stored object each.

        Read from the array's ``zarr.json`` directly (``shape`` and the regular ``chunk_grid`` of the
        Zarr v3 spec): opening each array through zarr costs ~0.7 ms, ten times that.
        """
        relative = f"{self.relative}/{name}/zarr.json"
        try:
            metadata = json.loads(self.location.read_bytes(relative))
            shape, grid = metadata["shape"], metadata["chunk_grid"]["configuration"]["chunk_shape"]
            return math.prod(-(-int(size) // int(step)) for size, step in zip(shape, grid, strict=True))
        except FileNotFoundError:
            raise self._damage(f"array {name} is missing") from None
        except (*DAMAGE, ArithmeticError) as exc:
            raise self._damage(f"unreadable metadata {name}/zarr.json ({first_line(exc)})", cause=exc) from exc

    def _listing(self) -> set[str]:
        """Non-empty files of the group, relative to it (temporaries left out); listed once."""
        if self._files is None:
            if self.location.is_local:
                relative: Iterable[str] = local_files(self.location.path(self.relative))
            else:
                root = self.location.path(self.relative).strip("/")
                try:
                    found = self.location.fs.find(self.location.path(self.relative), detail=True)
                except FileNotFoundError:
                    found = {}
                sized = (str(path).strip("/") for path, info in found.items() if info.get("size"))
                relative = (path.removeprefix(root).strip("/") for path in sized)
            self._files = {path for path in relative if not is_temporary(path)}
        return self._files

    def array_dtype(self, name: str) -> np.dtype[Any]:
        return np.dtype(self._array(name).dtype)

    def rows(self, name: str) -> RowTaker:
        """Rows of key array ``name``, each inner chunk decoded once, when first needed (cached): what a
        reader of one sample's window uses instead of the whole array."""
        if name not in self._takers:
            self._takers[name] = RowTaker(self, name)
        return self._takers[name]

    def key_set(self, name: str, row: int) -> npt.NDArray[np.int16]:
        """Rows ``offsets[row]:offsets[row + 1]`` of ``<name>_keys``."""
        offsets = self.array(f"{name}_offsets")
        return self.array(f"{name}_keys")[offsets[row] : offsets[row + 1]]
