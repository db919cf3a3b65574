"""Zarr v3 shard groups: write a task's arrays once each, read them back in whole blocks.

Small arrays (masks, offsets) are one chunk. Key arrays are chunked in blocks of `KEY_CHUNK_ROWS`
rows inside one sharded file, so a reader can fetch one sample's rows without the whole array. A
version-4 ``points_keys`` (each cloud in `schemas.shard.point_order`) is chunked in blocks of
`POINT_CHUNK_ROWS`, so that a window of a cloud's stored order decodes only the chunks it meets.
"""

from __future__ import annotations

import json
import math
import posixpath
import zipfile
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
import zarr
import zarr.codecs
from zarr.core.array_spec import ArrayConfigParams
from zarr.core.buffer import default_buffer_prototype
from zarr.storage import MemoryStore

from schemas.shard import ShardAttributes, array_names, ordered_points, single_file
from storage.shards.codec import COMPRESSORS, RowTaker, decoded_whole, encoded_row_shard
from storage.shards.group_files import GroupFiles, group_files, zarr_store, zip_bytes
from storage.store.errors import is_store_failure, storage_failure
from storage.store.location import Location, damaged, first_line

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


def write_shard_group(
    location: Location, relative: str, attributes: ShardAttributes, arrays: dict[str, npt.NDArray[Any]]
) -> int | None:
    """Write every array of a shard group once (the group is new: one attempt, one path): a folder of
    files for layouts 1-4, one ZIP of the same members from layout 5 (`schemas.shard.single_file`).
    Returns the bytes written when the group is one file."""
    missing = sorted(set(array_names(attributes.schema_version)) - set(arrays))
    if missing:
        raise ValueError(f"shard arrays missing: {missing}")
    if single_file(attributes.schema_version):
        members: dict[str, Any] = {}
        _fill_group(MemoryStore(members), attributes, arrays, members.__setitem__)
        blob = zip_bytes({name: members[name].to_bytes() for name in members})
        location.write_atomic(relative, blob)
        return len(blob)

    def put(member: str, blob: Any) -> None:
        target = location.path(f"{relative}/{member}")
        location.fs.makedirs(posixpath.dirname(target), exist_ok=True)
        location.fs.pipe_file(target, blob.to_bytes())

    _fill_group(zarr_store(location, relative, read_only=False), attributes, arrays, put)
    return None


def _fill_group(
    store: Any, attributes: ShardAttributes, arrays: dict[str, npt.NDArray[Any]], put: Callable[[str, Any], None]
) -> None:
    """Create the group's arrays in ``store`` and write their data; a sharded key array's one shard
    file is encoded here (`storage.shards.encoded_row_shard`) and handed to ``put`` (member, buffer)."""
    group = zarr.open_group(store, mode="w")
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
        if not data.size:
            continue
        blob = encoded_row_shard(data, dict(array.metadata.to_dict()))
        if blob is None:
            array[...] = data
        else:  # the same bytes zarr writes, for a fraction of its CPU
            put(f"{name}/c/0/0", default_buffer_prototype().buffer.from_bytes(blob))
    group.attrs.put(attributes.model_dump(mode="json"))


DAMAGE = (OSError, ValueError, KeyError, TypeError, IndexError, RuntimeError, EOFError, zipfile.BadZipFile)
"""What zarr, numcodecs and the stores raise on a missing, truncated or corrupt file (a CRC32C
mismatch is a ValueError, a missing member a KeyError, bad metadata a JSONDecodeError or a
validation error, a short Blosc frame a RuntimeError)."""


class ShardReader:
    """Read access to one committed shard group; whole arrays are cached after first use.

    Every failure to read the group is a `DamagedFile` naming the shard (path relative to the
    dataset) and the fix; `verify` (run on opening unless ``verify=False``) also finds what zarr
    would otherwise hide: a missing or emptied chunk file reads back as the fill value (zeros),
    silently. `storage.validate` opens without it and reports each finding as a line instead.
    """

    def __init__(
        self, location: Location, relative: str, verify: bool = True, span: tuple[str, int, int] | None = None
    ) -> None:
        self.location = location
        self.relative = relative
        self.files: GroupFiles = group_files(location, relative, span)
        """The group's members (a folder's files, or one ZIP's; ``span``: a byte range of a pack)."""
        self._cache: dict[str, npt.NDArray[Any]] = {}
        self._takers: dict[str, RowTaker] = {}
        self._nodes: dict[str, zarr.Array[Any]] = {}
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
        arrays (`storage.shards.whole_array`) never opens it (about 1 ms a shard, most of it zarr waking
        its event loop thread)."""
        if self._zarr_group is None:
            try:
                self._zarr_group = zarr.open_group(self.files.zarr_store(), mode="r")
            except FileNotFoundError as exc:
                raise self._damage("the shard group is missing") from exc
            except zipfile.BadZipFile as exc:
                problem = f"the shard file is not a readable ZIP ({first_line(exc)}); it is truncated or corrupt"
                raise self._damage(problem) from exc
            except DAMAGE as exc:
                raise self._damage(f"unreadable group metadata zarr.json ({first_line(exc)})", cause=exc) from exc
        return self._zarr_group

    def _plain_attributes(self) -> ShardAttributes | None:
        """The shard's attributes read from its group ``zarr.json`` directly, when that file is a plain
        Zarr v3 group as the writer writes it (nothing but its attributes) and they validate; else None,
        and zarr opens the group, raising the reader's usual errors for what is wrong with it."""
        try:
            meta = json.loads(self.files.read("zarr.json"))
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
        """A whole array (cached): decoded by `storage.shards.codec` where it has the layout written here (zarr's
        per-chunk machinery costs several times the decompression of a version-4 ``points_keys``'
        hundreds of small chunks), through zarr otherwise and for every failure, which names the damage."""
        if name not in self._cache:
            found = decoded_whole(self.files, name)
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
        try:
            metadata = json.loads(self.files.read(f"{name}/zarr.json"))
            shape, grid = metadata["shape"], metadata["chunk_grid"]["configuration"]["chunk_shape"]
            return math.prod(-(-int(size) // int(step)) for size, step in zip(shape, grid, strict=True))
        except FileNotFoundError:
            raise self._damage(f"array {name} is missing") from None
        except (*DAMAGE, ArithmeticError) as exc:
            raise self._damage(f"unreadable metadata {name}/zarr.json ({first_line(exc)})", cause=exc) from exc

    def _listing(self) -> set[str]:
        """Non-empty members of the group (temporaries left out); listed once."""
        return self.files.members()

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
