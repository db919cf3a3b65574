"""The per-sample fields of a `storage.batch.SampleBatch` read from a shard's arrays, one registry.

Each `SampleField` reads its values for some rows of one shard the same way for every batch reader
(`storage.memory`, `storage.stream`): a new field is its `SampleBatch` attribute and one
`register_field`. A view's gain reaches a network normalised by its task's denominator, the best next
view is `storage.gains.best_views`'s, and a case's occupancy grid is built from the task's per-view
ray cells (`storage.occupancy`) only when asked for.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from schemas.shard import (
    COVERAGE_GAINS,
    GAIN_TOTALS,
    GRID_HITS,
    GRID_MISSES,
    MASKS,
    VIEW_GAINS,
    VIEW_STATE_COLUMN,
    offsets_array,
)
from storage.batch import SampleBatch, Source
from storage.gains import best_views
from storage.occupancy import case_grid


@dataclass(frozen=True)
class ShardRows:
    """Some samples of one shard, as a reader has them: what a `SampleField` reads from."""

    source: Source
    local: npt.NDArray[np.int64]
    """The samples' rows within the shard."""
    array: Callable[[str], npt.NDArray[Any]]
    """The shard's array of that name, whole (`schemas.shard`'s names)."""


@dataclass(frozen=True)
class SampleField:
    """A per-sample `SampleBatch` field read from a shard's arrays, the same way by every batch reader.

    ``read`` gives the values of ``rows.local`` stacked, (S, ...) with a fixed trailing shape, for a
    dataset of schema version ``since`` or later. A new field of a sample is its `SampleBatch`
    attribute and one `register_field` here: `storage.memory` and `storage.stream` read and batch
    every registered field without naming it.
    """

    name: str
    since: int
    read: Callable[[ShardRows], npt.NDArray[Any]]
    optional: bool = False
    """Read only when a reader is asked for it by name (large, or costly to build)."""


SAMPLE_FIELDS: dict[str, SampleField] = {}
"""Every registered per-sample field, by `SampleBatch` attribute."""


def register_field(
    name: str, since: int = 1, optional: bool = False
) -> Callable[[Callable[[ShardRows], npt.NDArray[Any]]], Callable[[ShardRows], npt.NDArray[Any]]]:
    """Register the decorated reader as field ``name`` (a `SampleBatch` attribute) of datasets of
    schema version ``since`` or later; an ``optional`` one is read only when asked for."""
    if name not in {field.name for field in fields(SampleBatch)}:
        raise ValueError(f"{name!r} is no SampleBatch field; declare it on SampleBatch first")

    def register(read: Callable[[ShardRows], npt.NDArray[Any]]) -> Callable[[ShardRows], npt.NDArray[Any]]:
        if name in SAMPLE_FIELDS:
            raise ValueError(f"sample field {name!r} is registered twice")
        SAMPLE_FIELDS[name] = SampleField(name, since, read, optional)
        return read

    return register


def fields_for(schema_version: int, asked: Sequence[str] = ()) -> list[SampleField]:
    """The registered fields a reader of a dataset of ``schema_version`` reads, sorted by name: every
    one the version has, the optional ones only when ``asked`` names them. Naming a field that is not
    registered, or that the version lacks, is a `ValueError`."""
    for name in asked:
        found = SAMPLE_FIELDS.get(name)
        if found is None:
            known = ", ".join(sorted(SAMPLE_FIELDS))
            raise ValueError(f"fields: {name!r} is no sample field; the fields are {known}")
        if found.since > schema_version:
            raise ValueError(
                f"fields: {name!r} needs a dataset of schema version {found.since}; this one is version "
                f"{schema_version} (add it with `datagen shards relabel`)"
            )
    return [
        field
        for name, field in sorted(SAMPLE_FIELDS.items())
        if field.since <= schema_version and (not field.optional or name in asked)
    ]


@register_field("cloud_size")
def _cloud_size(rows: ShardRows) -> npt.NDArray[np.int64]:
    offsets = np.asarray(rows.array(offsets_array(rows.source)), dtype=np.int64)
    return offsets[rows.local + 1] - offsets[rows.local]


def _cases(rows: ShardRows) -> npt.NDArray[np.uint64]:
    return np.asarray(rows.array(MASKS), dtype=np.uint64)[rows.local, VIEW_STATE_COLUMN]


@register_field("view_gain", since=3)
def _view_gain(rows: ShardRows) -> npt.NDArray[np.float32]:
    gains = np.asarray(rows.array(VIEW_GAINS))[rows.local]
    return _normalised(gains, int(rows.array(GAIN_TOTALS)[0]))


@register_field("coverage_gain", since=3)
def _coverage_gain(rows: ShardRows) -> npt.NDArray[np.float32]:
    gains = np.asarray(rows.array(COVERAGE_GAINS))[rows.local]
    return _normalised(gains, int(rows.array(GAIN_TOTALS)[1]))


@register_field("best_view", since=3)
def _best_view(rows: ShardRows) -> npt.NDArray[np.int64]:
    gains = np.asarray(rows.array(VIEW_GAINS))[rows.local]
    return best_views(gains, _cases(rows), gains.shape[1])[0]


@register_field("grid", since=3, optional=True)
def _grid(rows: ShardRows) -> npt.NDArray[np.float32]:
    hits, misses = rows.array(GRID_HITS), rows.array(GRID_MISSES)
    grids = [case_grid(hits, misses, case) for case in _cases(rows).tolist()]
    return np.stack(grids) if grids else np.zeros((0, 32, 32, 32), dtype=np.float32)


def _normalised(gains: npt.NDArray[Any], total: int) -> npt.NDArray[np.float32]:
    """Gains over their denominator, in float64 then float32 (0 when nothing is counted)."""
    return (gains.astype(np.float64) / total if total else np.zeros(gains.shape)).astype(np.float32)
