"""Every field of a `storage.samples.SampleBatch`, one registry: how each is read from a shard and batched.

A `SampleField` has two steps, the same for every reader (`storage.readers.memory`, `storage.stream`,
`storage.torch`; the path itself is `storage.samples.assemble`):

1. ``hold``: its values for some rows of one shard (`ShardRows`), as a `storage.samples.Held` the
   reader keeps: the in-memory reader for the whole load, the stream in its shuffle buffer, the
   map-style reader for one item;
2. ``finish``: the arrays of a batch from the held values of its samples (`BatchFacts`: the
   dataset's grid and views, the batch's dataset rows and how its clouds are drawn).

The cloud (``points``) is held whole where a reader draws it per batch (memory: another draw every
epoch) and drawn at once where it reads per epoch (`ShardRows.draw`: the stream, the map-style
reader), from the same streams (seed, epoch, dataset row), so every reader gives the same arrays.
A new field is one `register_field` (a module of its own is enough: a name `SampleBatch` does not
declare lands in its ``extra``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from schemas.registry import Registry
from schemas.shard import (
    COVERAGE_GAINS,
    COVERS,
    GAIN_TOTALS,
    GRID_HITS,
    GRID_MISSES,
    LABEL_COLUMN,
    MASKS,
    VIEW_GAINS,
    VIEW_STATE_COLUMN,
    keys_array,
    offsets_array,
)
from storage.samples.batch import Source
from storage.samples.bits import bit_rows, padded_covers
from storage.samples.covers import listed_marginals
from storage.samples.gains import best_views
from storage.samples.held import Held, Positions, Ragged, Stacked
from storage.samples.occupancy_grid import GRID_SIDE, case_grid
from storage.samples.resampling import gather_clouds, key_centres, resample_many_keys, windowed_cloud

Values = npt.NDArray[Any]


@dataclass(frozen=True)
class Draw:
    """How clouds are drawn: ``num_points`` each, from stream (seed, epoch, dataset row)."""

    num_points: int
    seed: int
    epoch: int


@dataclass(frozen=True)
class ShardRows:
    """Some samples of one shard, as a reader has them: what a field's ``hold`` reads from."""

    source: Source
    local: Positions
    """The samples' rows within the shard."""
    array: Callable[[str], Values]
    """The shard's array of that name, whole (`schemas.shard`'s names)."""
    rows: Positions | None = None
    """The samples' dataset rows (their resampling streams); None: ``local``."""
    schema_version: int = 1
    num_views: int = 32
    column: Callable[[str], Values] | None = None
    """An index column's values of these samples (the columns a field declares)."""
    taker: Callable[[str], Callable[[Positions], Values]] | None = None
    """Rows of a key array, decoding only the chunks a take meets (a version-4 window); None: the
    whole array."""
    draw: Draw | None = None
    """Draw the clouds now (a reader that reads every epoch); None: hold them whole."""

    @property
    def dataset_rows(self) -> Positions:
        return self.local if self.rows is None else self.rows

    def take_rows(self, name: str) -> Callable[[Positions], Values]:
        if self.taker is not None:
            return self.taker(name)
        return self.array(name).__getitem__

    def index_column(self, name: str) -> Values:
        if self.column is None:
            raise ValueError(f"this reader gives no index column {name!r}")
        return self.column(name)


@dataclass(frozen=True)
class BatchFacts:
    """What finishing a batch needs besides its samples' held values."""

    num_views: int
    voxel_size: float
    grid_offset: npt.NDArray[np.float64]
    schema_version: int
    source: Source
    rows: Positions
    """The batch's dataset rows, in batch order."""
    draw: Draw | None = None
    """How clouds held whole are drawn (the in-memory reader)."""


Hold = Callable[[ShardRows], "Held | Values"]
Finish = Callable[[Held, Positions, BatchFacts], Values]


def stacked_values(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    """The default ``finish``: the held rows of the batch's samples as they are."""
    assert isinstance(held, Stacked)
    return held.values[positions]


@dataclass(frozen=True)
class SampleField:
    """One `SampleBatch` field: read by ``hold`` for some rows of a shard, batched by ``finish``
    (``finish(held, positions, facts)``: the batch is the samples at ``positions`` of ``held``)."""

    name: str
    since: int
    hold: Hold
    finish: Finish = stacked_values
    optional: bool = False
    """Read only when a reader is asked for it by name (large, or costly to build)."""
    covers: bool = False
    """Needs a dataset that keeps minimum covers (version 2 and later)."""
    padded: bool = False
    """Its shape depends on the batch (padded to the batch's longest sample): no per-item reader gives it."""
    columns: tuple[str, ...] = ()
    """Index columns ``hold`` reads (`ShardRows.column`)."""

    def held(self, rows: ShardRows) -> Held:
        found = self.hold(rows)
        return found if not isinstance(found, np.ndarray) else Stacked(found)


SAMPLE_FIELDS: Registry[SampleField] = Registry(
    "sample field", "datagen.sample_fields", error=ValueError, check=lambda entry: isinstance(entry, SampleField)
)
"""Every registered field, by name; a package adds one as an entry point of the group
``datagen.sample_fields`` naming its `SampleField` (or a module whose `register_field` calls run on import)."""

CORE_FIELDS = ("points", "view_state", "label", "index")
"""The fields every batch has."""


def register_field(
    name: str,
    since: int = 1,
    optional: bool = False,
    *,
    finish: Finish = stacked_values,
    covers: bool = False,
    padded: bool = False,
    columns: tuple[str, ...] = (),
) -> Callable[[Hold], Hold]:
    """Register the decorated ``hold`` as field ``name`` of datasets of schema version ``since`` or
    later (``covers``: of datasets keeping minimum covers); an ``optional`` one is read only when
    asked for. A name `SampleBatch` declares is that attribute; any other is in ``batch.extra``."""
    if not name.isidentifier() or name in ("extra",):
        raise ValueError(f"{name!r} cannot name a sample field")

    def register(hold: Hold) -> Hold:
        SAMPLE_FIELDS.register(name, SampleField(name, since, hold, finish, optional, covers, padded, columns))
        return hold

    return register


def fields_for(schema_version: int, asked: Sequence[str] = (), has_covers: bool = False) -> list[SampleField]:
    """The fields a reader of a dataset of ``schema_version`` (``has_covers``: one keeping minimum
    covers) reads, sorted by name: every one the dataset has, the optional ones only when ``asked``
    names them. Naming a field that is not registered, or that the dataset lacks, is a `ValueError`."""
    for name in asked:
        found = SAMPLE_FIELDS.get(name)
        if found is None:
            known = ", ".join(sorted(SAMPLE_FIELDS))
            raise ValueError(f"fields: {name!r} is no sample field; the fields are {known}")
        if found.since > schema_version or (found.covers and not has_covers):
            version = max(found.since, 2) if found.covers else found.since
            raise ValueError(
                f"fields: {name!r} needs a dataset of schema version {version}; this one is version "
                f"{schema_version} (add it with `datagen shards relabel`)"
            )
    return [
        field
        for name, field in sorted(SAMPLE_FIELDS.items())
        if field.since <= schema_version and (has_covers or not field.covers) and (not field.optional or name in asked)
    ]


# -- the cloud ---------------------------------------------------------------------------------


def _finish_points(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    """(B, N, 3) float32 key centres: drawn now from whole clouds, or as drawn when read."""
    if isinstance(held, Ragged):
        if facts.draw is None:
            raise ValueError("clouds held whole need the batch's draw (num_points, seed, epoch)")
        draw = facts.draw
        windowed = windowed_cloud(facts.schema_version, facts.source)
        starts = held.offsets[positions]
        sizes = held.offsets[positions + 1] - starts
        keys = gather_clouds(
            held.values.__getitem__, starts, sizes, facts.rows, draw.num_points, draw.seed, draw.epoch, windowed
        )
    else:
        assert isinstance(held, Stacked)
        keys = held.values[positions]
    return key_centres(keys, facts.voxel_size, facts.grid_offset)


@register_field("points", finish=_finish_points)
def _points(rows: ShardRows) -> Held:
    """The sample's cloud: whole (`Ragged` keys), or drawn now (`Stacked` (S, N, 3) keys) by the sample
    contract: a version-4 refined cloud as one window of its stored order, decoding only the chunks
    the windows meet; any other cloud read whole and drawn by `storage.resample_many_keys`."""
    offsets = np.asarray(rows.array(offsets_array(rows.source)), dtype=np.int64)
    name = keys_array(rows.source)
    if rows.draw is None:
        return Ragged.of_rows(rows.array(name), offsets, rows.local)
    draw, streams = rows.draw, rows.dataset_rows
    if windowed_cloud(rows.schema_version, rows.source):
        first = offsets[rows.local]
        sizes = offsets[rows.local + 1] - first
        drawn = gather_clouds(rows.take_rows(name), first, sizes, streams, draw.num_points, draw.seed, draw.epoch, True)
        return Stacked(drawn)
    keys = rows.array(name)
    starts, ends = offsets[rows.local].tolist(), offsets[rows.local + 1].tolist()
    clouds = [keys[start:end] for start, end in zip(starts, ends, strict=True)]
    resampled = resample_many_keys(clouds, draw.num_points, draw.seed, draw.epoch, streams.tolist())
    return Stacked(np.stack(resampled) if resampled else np.zeros((0, draw.num_points, 3), dtype=np.int16))


@register_field("cloud_size")
def _cloud_size(rows: ShardRows) -> npt.NDArray[np.int64]:
    """(B,) int64: points in the stored cloud ``points`` was drawn from."""
    offsets = np.asarray(rows.array(offsets_array(rows.source)), dtype=np.int64)
    return offsets[rows.local + 1] - offsets[rows.local]


# -- the case and its label --------------------------------------------------------------------


def _finish_bits(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    """Masks as (B, n) float32 0/1 rows (bit v = view v)."""
    assert isinstance(held, Stacked)
    return bit_rows(held.values[positions], facts.num_views)


def _masks(rows: ShardRows, column: int) -> npt.NDArray[np.uint64]:
    return np.asarray(rows.array(MASKS), dtype=np.uint64)[rows.local, column]


@register_field("view_state", finish=_finish_bits)
def _view_state(rows: ShardRows) -> npt.NDArray[np.uint64]:
    return _masks(rows, VIEW_STATE_COLUMN)


@register_field("label", finish=_finish_bits)
def _label(rows: ShardRows) -> npt.NDArray[np.uint64]:
    return _masks(rows, LABEL_COLUMN)


@register_field("index")
def _index(rows: ShardRows) -> npt.NDArray[np.int64]:
    """(B,) int64: each sample's dataset row (its resampling stream)."""
    return np.array(rows.dataset_rows, dtype=np.int64)


# -- minimum covers (version 2) ----------------------------------------------------------------


@register_field("marginals", since=2, covers=True)
def _marginals(rows: ShardRows) -> npt.NDArray[np.float32]:
    """(B, n) float32: the fraction of the listed minimum covers holding each view."""
    listed = listed_marginals(rows.array(COVERS), rows.array(offsets_array(COVERS)), rows.local, rows.num_views)
    return listed.astype(np.float32)


@register_field("support", since=2, covers=True, columns=("label_support",), finish=_finish_bits)
def _support(rows: ShardRows) -> npt.NDArray[np.uint64]:
    """The views in any minimum cover (exact even where the listing is capped)."""
    return np.asarray(rows.index_column("label_support"), dtype=np.uint64)


def _finish_covers(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    assert isinstance(held, Ragged)
    return padded_covers([held.of(p) for p in positions.tolist()], facts.num_views)[0]


@register_field("covers", since=2, optional=True, covers=True, padded=True, finish=_finish_covers)
def _covers(rows: ShardRows) -> Ragged:
    """(B, C, n) float32 0/1: the listed minimum covers, padded to the batch's longest listing."""
    listed = np.asarray(rows.array(COVERS), dtype=np.uint64)
    return Ragged.of_rows(listed, rows.array(offsets_array(COVERS)), rows.local)


def _finish_cover_mask(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    """(B, C) bool: True where ``covers`` holds a real cover (C as `storage.samples.padded_covers`'s)."""
    assert isinstance(held, Stacked)
    counts = held.values[positions]
    most = int(counts.max()) if counts.size else 0
    return np.arange(most)[None, :] < counts[:, None]


@register_field("cover_mask", since=2, optional=True, covers=True, padded=True, finish=_finish_cover_mask)
def _cover_mask(rows: ShardRows) -> npt.NDArray[np.int64]:
    offsets = np.asarray(rows.array(offsets_array(COVERS)), dtype=np.int64)
    return offsets[rows.local + 1] - offsets[rows.local]


COVER_FIELDS = ("covers", "cover_mask")
"""What a reader asked for the listed covers reads."""


# -- the next view (version 3) -----------------------------------------------------------------


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
    return best_views(gains, _masks(rows, VIEW_STATE_COLUMN), gains.shape[1])[0]


def _normalised(gains: npt.NDArray[Any], total: int) -> npt.NDArray[np.float32]:
    """Gains over their denominator, in float64 then float32 (0 when nothing is counted)."""
    return (gains.astype(np.float64) / total if total else np.zeros(gains.shape)).astype(np.float32)


@dataclass(frozen=True)
class CaseGrids:
    """Samples' occupancy grids, built when batched from their tasks' per-view ray cells (the shard's
    ``grid_hits`` and ``grid_misses``, kept once per task, a few hundred bytes a sample instead of
    the 128 KB of a grid): a `storage.samples.Held` of the ``grid`` field."""

    hits: npt.NDArray[np.uint8]
    """(T, n, PACKED_CELLS) each held task's cells its views' rays end in."""
    misses: npt.NDArray[np.uint8]
    """(T, n, PACKED_CELLS) the cells they only cross."""
    task: npt.NDArray[np.int64]
    """(S,) the task of each sample (an index into ``hits``)."""
    cases: npt.NDArray[np.uint64]
    """(S,) each sample's view-state mask: the views its grid holds."""

    def __len__(self) -> int:
        return int(self.task.size)

    def take(self, positions: Positions) -> CaseGrids:
        return CaseGrids(self.hits, self.misses, self.task[positions], self.cases[positions])

    @classmethod
    def placed(cls, pieces: Sequence[tuple[Positions, CaseGrids]], total: int) -> CaseGrids:
        task = np.zeros(total, dtype=np.int64)
        cases = np.zeros(total, dtype=np.uint64)
        first = 0
        for positions, held in pieces:
            task[positions] = held.task + first
            cases[positions] = held.cases
            first += held.hits.shape[0]
        hits = np.concatenate([held.hits for _, held in pieces])
        misses = np.concatenate([held.misses for _, held in pieces])
        return CaseGrids(hits, misses, task, cases)

    def grids(self, positions: Positions) -> npt.NDArray[np.float32]:
        """(B, 32, 32, 32) float32 occupancy probabilities of the samples at ``positions``."""
        found = [
            case_grid(self.hits[task], self.misses[task], case)
            for task, case in zip(self.task[positions].tolist(), self.cases[positions].tolist(), strict=True)
        ]
        return np.stack(found) if found else np.zeros((0, GRID_SIDE, GRID_SIDE, GRID_SIDE), dtype=np.float32)


def _finish_grid(held: Held, positions: Positions, facts: BatchFacts) -> Values:
    assert isinstance(held, CaseGrids)
    return held.grids(positions)


@register_field("grid", since=3, optional=True, finish=_finish_grid)
def _grid(rows: ShardRows) -> CaseGrids:
    """(B, 32, 32, 32) float32: the case's occupancy probabilities indexed [x, y, z], 0.5 unknown."""
    hits, misses = np.asarray(rows.array(GRID_HITS)), np.asarray(rows.array(GRID_MISSES))
    task = np.zeros(rows.local.size, dtype=np.int64)
    return CaseGrids(hits[None], misses[None], task, _masks(rows, VIEW_STATE_COLUMN))
