"""The samples a reader holds: where each one lives (its shard and row) and, when asked, its index columns.

A dataset of 100,000 tasks holds about six million samples; its whole index in memory (about 35
columns, a third of them strings) would take gigabytes. A reader needs only where each sample lives,
which the manifest's tasks table says in a few MB (a task's samples are consecutive, in shard row
order): `SampleIndex` keeps that as two small integer arrays and reads any other column from the
manifest's samples tables the first time it is asked for, one column at a time. A dataset finalised by
earlier code, or one never finalised, has its index in memory anyway and is read from that table.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from schemas.index import INDEX_SCHEMAS
from storage.dataset.manifest import (
    Manifest,
    count_values,
    read_samples,
    read_samples_column,
    read_samples_group,
    read_samples_row,
)
from storage.store.location import Location, damaged

KEPT_GROUPS = 8
"""Row groups of a column a manifest reader keeps for single values (`ManifestColumns.value`)."""
Span = tuple[str, int, int]
"""Where a packed task's shard lies: the pack file, the offset and the size of its ZIP there."""


class Columns(Protocol):
    """Where the index columns of every sample of a dataset come from."""

    def column(self, name: str) -> pa.ChunkedArray: ...

    def table(self) -> pa.Table: ...

    def row(self, position: int) -> dict[str, Any]:
        """Every column of one row."""
        ...

    def value(self, position: int, name: str) -> Any:
        """One column of one row."""
        ...

    def counts(self, name: str) -> dict[Any, int]:
        """How many rows hold each value of a column."""
        ...

    @property
    def names(self) -> list[str]: ...


@dataclass(frozen=True)
class TableColumns:
    """Columns of an index held in memory (a legacy ``index.parquet``, or merged fragments)."""

    index: pa.Table

    def column(self, name: str) -> pa.ChunkedArray:
        return self.index.column(name)

    def table(self) -> pa.Table:
        return self.index

    def row(self, position: int) -> dict[str, Any]:
        return dict(self.index.slice(position, 1).to_pylist()[0])

    def value(self, position: int, name: str) -> Any:
        return self.index.column(name)[position].as_py()

    def counts(self, name: str) -> dict[Any, int]:
        return _counted(self.index.column(name))

    @property
    def names(self) -> list[str]:
        return list(self.index.column_names)


@dataclass(frozen=True)
class ManifestColumns:
    """Columns of the manifest's samples tables, then of the tasks committed since (``tail``, merged
    from their fragments), read one at a time on first use."""

    location: Location
    manifest: Manifest
    tail: pa.Table | None = None
    """The index rows of the tasks committed since the manifest was written (None: none)."""
    _groups: dict[str, dict[tuple[int, int], pa.Array]] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_groups"] = {}  # read again where it travels
        return state

    def column(self, name: str) -> pa.ChunkedArray:
        if name not in self.names:
            raise KeyError(f"no index column {name!r}")
        stored = read_samples_column(self.location, self.manifest, name)
        if self.tail is None:
            return stored
        return pa.chunked_array([*stored.chunks, *self.tail.column(name).chunks], type=stored.type)

    def table(self) -> pa.Table:
        stored = read_samples(self.location, self.manifest)
        return stored if self.tail is None else pa.concat_tables([stored, self.tail]).combine_chunks()

    def counts(self, name: str) -> dict[Any, int]:
        found = count_values(self.location, self.manifest, name)
        if self.tail is not None:
            for value, count in _counted(self.tail.column(name)).items():
                found[value] = found.get(value, 0) + count
        return found

    def value(self, position: int, name: str) -> Any:
        """One column of one row, from the row group that holds it (the last few read are kept: a reader
        walking a shard's samples reads each group once)."""
        if position >= self.manifest.num_samples and self.tail is not None:
            return self.tail.column(name)[position - self.manifest.num_samples].as_py()
        groups = self._groups.setdefault(name, {})
        for (start, stop), values in groups.items():
            if start <= position < stop:
                return values[position - start].as_py()
        found = read_samples_group(self.location, self.manifest, position, name)
        if found is None:
            raise IndexError(f"row {position} outside the index")
        (start, stop), values = found
        if len(groups) >= KEPT_GROUPS:
            groups.pop(next(iter(groups)))
        groups[(start, stop)] = values
        return values[position - start].as_py()

    def row(self, position: int) -> dict[str, Any]:
        """One row, reading only the row group that holds it."""
        found = read_samples_row(self.location, self.manifest, position)
        if found is None and self.tail is not None:
            return dict(self.tail.slice(position - self.manifest.num_samples, 1).to_pylist()[0])
        if found is None:
            raise IndexError(f"row {position} outside the index")
        return found

    @property
    def names(self) -> list[str]:
        return list(INDEX_SCHEMAS[self.manifest.schema_version].names)


@dataclass
class SampleIndex:
    """Samples in reading order: sample i lives at row ``rows[i]`` of shard ``shards[codes[i]]``;
    ``positions`` are their rows in the dataset's whole index (None: all of it, in order)."""

    shards: list[str]
    codes: npt.NDArray[np.int32]
    rows: npt.NDArray[np.int32]
    source: Columns
    spans: dict[str, Span] = field(default_factory=dict)
    positions: npt.NDArray[np.int64] | None = None
    tasks: pa.Table | None = None
    """The dataset's tasks (`storage.dataset.manifest.TASKS_SCHEMA`) when a manifest named them; None otherwise."""
    _columns: dict[str, pa.ChunkedArray] = field(default_factory=dict, repr=False)
    _table: pa.Table | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.codes.size)

    def shard(self, i: int) -> str:
        return self.shards[int(self.codes[i])]

    def span(self, shard: str) -> Span | None:
        return self.spans.get(shard)

    @property
    def column_names(self) -> list[str]:
        return self.source.names

    def column(self, name: str, keep: bool = True) -> pa.ChunkedArray:
        """Index column ``name`` of the held samples (read once; ``keep=False``: not kept, for a caller
        that keeps its own copy)."""
        found = self._columns.get(name)
        if found is None:
            if self._table is not None:
                found = self._table.column(name)
            else:
                whole = self.source.column(name)
                found = whole if self.positions is None else whole.take(pa.array(self.positions))
            if keep:
                self._columns[name] = found
        return found

    def value(self, i: int, name: str) -> Any:
        """Index column ``name`` of held sample ``i`` (its row group's when read from a manifest)."""
        found = self._columns.get(name)
        if found is not None:
            return found[i].as_py()
        if self._table is not None:
            return self._table.column(name)[i].as_py()
        return self.source.value(int(i if self.positions is None else self.positions[i]), name)

    def counts(self, name: str) -> dict[Any, int]:
        """How many held samples hold each value of column ``name``, sorted by value (the whole dataset's
        read a row group at a time, a selection's from the column)."""
        found = self.source.counts(name) if self.positions is None else _counted(self.column(name))
        return dict(sorted(found.items()))

    def row(self, i: int) -> dict[str, Any]:
        """Every index column of held sample ``i`` (from its row group alone when read from a manifest)."""
        if self._table is not None:
            return dict(self._table.slice(i, 1).to_pylist()[0])
        return self.source.row(int(i if self.positions is None else self.positions[i]))

    def table(self) -> pa.Table:
        """Every index column of the held samples (the whole index in memory: what a large dataset's
        reader avoids; `column` reads one)."""
        if self._table is None:
            whole = self.source.table()
            self._table = whole if self.positions is None else whole.take(pa.array(self.positions))
        return self._table

    def select(self, rows: npt.ArrayLike) -> SampleIndex:
        """The samples at ``rows`` of this index, in that order."""
        chosen = np.asarray(rows, dtype=np.int64).reshape(-1)
        positions = chosen if self.positions is None else self.positions[chosen]
        return SampleIndex(
            self.shards, self.codes[chosen], self.rows[chosen], self.source, self.spans, positions, self.tasks
        )

    def by_shard(self) -> list[npt.NDArray[np.int64]]:
        """Sample positions grouped by shard (shards sorted by path, positions ascending)."""
        if not len(self):
            return []
        rank = np.empty(len(self.shards), dtype=np.int64)
        rank[np.argsort(np.asarray(self.shards, dtype=object), kind="stable")] = np.arange(len(self.shards))
        keys = rank[self.codes]
        order = np.argsort(keys, kind="stable")
        bounds = np.flatnonzero(np.diff(keys[order])) + 1
        return [group.astype(np.int64) for group in np.split(order, bounds)]


def _counted(column: pa.ChunkedArray) -> dict[Any, int]:
    counted = pc.value_counts(column)
    return dict(zip(counted.field("values").to_pylist(), counted.field("counts").to_pylist(), strict=True))


def from_tasks(location: Location, tasks: pa.Table, source: Columns, packed: bool) -> SampleIndex:
    """The index of a manifest's tasks (`storage.dataset.manifest.TASKS_SCHEMA`, in sample order): each task's
    samples consecutive, in shard row order."""
    counts = numpy_of(tasks.column("num_samples")).astype(np.int64)
    shards = tasks.column("shard").to_pylist()
    codes = np.repeat(np.arange(len(shards), dtype=np.int32), counts)
    rows = np.arange(int(counts.sum()), dtype=np.int32)  # int32 throughout: 4 bytes a sample
    rows -= np.repeat((np.cumsum(counts) - counts).astype(np.int32), counts)
    spans: dict[str, Span] = {}
    if packed:
        for shard, pack, offset, size in zip(
            shards,
            tasks.column("pack").to_pylist(),
            tasks.column("pack_offset").to_pylist(),
            tasks.column("pack_size").to_pylist(),
            strict=True,
        ):
            if pack is None or offset is None or size is None:
                raise damaged(location.url, "index/manifest.json", f"the packed task of {shard} names no pack")
            spans[shard] = (pack, int(offset), int(size))
    return SampleIndex(_unique(shards, location), codes, rows, source, spans, tasks=tasks)


def numpy_of(column: pa.ChunkedArray) -> npt.NDArray[Any]:
    """A column as one numpy array, chunk by chunk. Numbers and booleans without nulls are read from
    their buffers: pyarrow's own ``to_numpy`` imports pandas (half a second) the first time it runs."""
    parts = [_chunk_numpy(chunk) for chunk in column.chunks]
    if not parts:
        return np.zeros(0, dtype=_NUMPY_TYPES.get(str(column.type), str(column.type)))
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


_NUMPY_TYPES = {"double": "float64", "float": "float32", "halffloat": "float16", "bool": "bool"}


def _chunk_numpy(chunk: pa.Array) -> npt.NDArray[Any]:
    kind = chunk.type
    if chunk.null_count == 0 and (pa.types.is_integer(kind) or pa.types.is_floating(kind)):
        dtype = np.dtype(_NUMPY_TYPES.get(str(kind), str(kind)))
        data = chunk.buffers()[1]
        return np.frombuffer(data, dtype=dtype, count=len(chunk), offset=chunk.offset * dtype.itemsize).copy()
    if chunk.null_count == 0 and pa.types.is_boolean(kind):
        bits = np.unpackbits(np.frombuffer(chunk.buffers()[1], dtype=np.uint8), bitorder="little")
        return bits[chunk.offset : chunk.offset + len(chunk)].astype(bool)
    return np.asarray(chunk.to_numpy(zero_copy_only=False))


def from_table(table: pa.Table) -> SampleIndex:
    """The index of a table holding every column (`shard` and `row` among them)."""
    encoded = pc.dictionary_encode(table.column("shard")).combine_chunks()
    shards = encoded.dictionary.to_pylist()
    codes = encoded.indices.to_numpy(zero_copy_only=False).astype(np.int32)
    rows = numpy_of(table.column("row")).astype(np.int32)
    return SampleIndex(shards, codes, rows, TableColumns(table))


def _unique(shards: list[str], location: Location) -> list[str]:
    if len(set(shards)) != len(shards):
        raise damaged(location.url, "index/manifest.json", "a shard is named by two tasks")
    return shards
