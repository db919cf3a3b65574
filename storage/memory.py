"""A dataset's samples in memory: read once, shard by shard, then batched without a reader.

A training epoch over a few thousand samples must not wait on Zarr reads, so `load_memory` reads
the integer keys of the chosen samples once (whole shard arrays, the reader's fast order) and keeps
them packed in one int16 array with offsets, with each sample's view state and label (as masks and
as 0/1 rows), object id, the dataset's voxel size, grid offset, schema version and stored config
hash, and, for a version-2 dataset, its minimum covers and U's set-cover rows packed as uint64 masks
with offsets. `MemoryDataset.batch` then builds fixed-size point clouds by a numpy gather. Asked for
the occupancy grids (``fields=("grid",)``), it keeps each task's per-view ray cells once (`CaseGrids`,
a few hundred bytes a sample) and builds a batch's grids when asked, instead of 128 KB per sample.

Every conversion follows the sample contract (`storage.resampling`, `storage.bits`, `storage.batch`):
a sample held at position ``p`` is resampled from stream ``(seed, epoch, rows[p])``, its row in the
dataset it was loaded from, so a side loaded alone (``rows=`` or ``objects=``) gives exactly the
tensors it gives in a whole load, and a whole load exactly what `storage.torch.OSVPDataset` gives
for the same (seed, epoch, index).

A version-4 dataset's refined clouds are drawn as windows of their stored order (`storage.resampling`);
memory still holds each whole cloud, since every epoch draws another window of it.

Depends on numpy and `storage` only: no torch here (osvp wraps the arrays as tensors).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow.compute as pc

from schemas.shard import (
    COVER_ROWS,
    COVERS,
    GRID_HITS,
    GRID_MISSES,
    LABEL_COLUMN,
    MASKS,
    VIEW_STATE_COLUMN,
    keys_array,
    offsets_array,
)
from storage.batch import SampleBatch, Source, check_source
from storage.bits import bit_rows
from storage.occupancy import GRID_SIDE, case_grid
from storage.reader import Dataset, open_dataset
from storage.resampling import gather_clouds, key_centres, windowed_cloud
from storage.sample_fields import ShardRows, fields_for

Progress = Callable[[int, int], None]
"""Called with (samples read, samples to read) after each shard."""
MaskArray = npt.NDArray[np.uint64]
Rows = Sequence[int] | npt.NDArray[np.integer]


GRID_FIELD = "grid"
"""The optional field `load_memory` holds as `CaseGrids` rather than as values per sample."""


@dataclass(frozen=True)
class CaseGrids:
    """Every held sample's occupancy grid, built on demand from its task's per-view ray cells (the
    shard's ``grid_hits`` and ``grid_misses``, kept once per task): the same arrays as the registered
    ``grid`` field (`storage.occupancy.case_grid`) without holding 128 KB per sample."""

    hits: npt.NDArray[np.uint8]
    """(T, n, PACKED_CELLS) each held task's cells its views' rays end in."""
    misses: npt.NDArray[np.uint8]
    """(T, n, PACKED_CELLS) the cells they only cross."""
    task: npt.NDArray[np.int64]
    """(S,) the task of each held sample (an index into ``hits``)."""
    cases: MaskArray
    """(S,) each held sample's view-state mask: the views its grid holds."""

    def grids(self, positions: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
        """(B, 32, 32, 32) float32 occupancy probabilities of the samples at ``positions``."""
        found = [
            case_grid(self.hits[task], self.misses[task], case)
            for task, case in zip(self.task[positions].tolist(), self.cases[positions].tolist(), strict=True)
        ]
        return np.stack(found) if found else np.zeros((0, GRID_SIDE, GRID_SIDE, GRID_SIDE), dtype=np.float32)


@dataclass(frozen=True)
class PackedCovers:
    """Every held sample's minimum covers and U's set-cover rows (schema version 2), as masks.

    Sample ``p``'s covers are ``covers[cover_offsets[p]:cover_offsets[p + 1]]`` (the label among
    them, as `storage.Dataset.ambiguity` lists them), its U rows (the view state's already left out)
    ``universe[universe_offsets[p]:universe_offsets[p + 1]]``."""

    covers: MaskArray
    cover_offsets: npt.NDArray[np.int64]
    universe: MaskArray
    universe_offsets: npt.NDArray[np.int64]
    support: MaskArray
    """(S,) mask of the views in any minimum cover (exact even when the listing is capped)."""
    counts: npt.NDArray[np.int64]
    """How many minimum covers exist (a lower bound where not ``exact``)."""
    exact: npt.NDArray[np.bool_]

    def covers_of(self, position: int) -> MaskArray:
        return self.covers[self.cover_offsets[position] : self.cover_offsets[position + 1]]

    def universe_of(self, position: int) -> MaskArray:
        return self.universe[self.universe_offsets[position] : self.universe_offsets[position + 1]]


@dataclass(frozen=True)
class MemoryDataset:
    """Samples of a dataset held in memory; position ``p`` is the dataset's row ``rows[p]``."""

    url: str
    config_hash: str
    """The dataset's own record (``dataset.json``), never recomputed: that would hash this
    machine's datagen files, not the dataset's."""
    schema_version: int
    num_views: int
    voxel_size: float
    grid_offset: npt.NDArray[np.float64]
    source: Source
    rows: npt.NDArray[np.int64]
    """(S,) the dataset row of each held sample: its resampling stream."""
    keys: npt.NDArray[np.int16]
    """(K, 3) every held sample's keys, packed in position order."""
    offsets: npt.NDArray[np.int64]
    """(S + 1,) sample ``p``'s keys are ``keys[offsets[p]:offsets[p + 1]]``."""
    view_state_masks: MaskArray
    label_masks: MaskArray
    view_state: npt.NDArray[np.float32]
    """(S, n) 0/1 rows of the view-state masks (bit v = view v)."""
    labels: npt.NDArray[np.float32]
    """(S, n) 0/1 rows of the label masks."""
    object_ids: tuple[str, ...]
    covers: PackedCovers | None = None
    """None for a version-1 dataset, or when the load was asked to leave them out."""
    fields: dict[str, npt.NDArray[Any]] = field(default_factory=dict)
    """(S, ...) values of every registered `storage.sample_fields.SampleField` the dataset has, by name
    (the grid excepted: `grids`)."""
    grids: CaseGrids | None = None
    """The occupancy grids when the load asked for them; a batch then carries ``grid``."""

    def __len__(self) -> int:
        return int(self.rows.size)

    def keys_of(self, position: int) -> npt.NDArray[np.int16]:
        """The integer keys (K, 3) of the sample held at ``position``."""
        return self.keys[self.offsets[position] : self.offsets[position + 1]]

    def resampled_keys(self, positions: Rows, num_points: int, seed: int, epoch: int) -> npt.NDArray[np.int16]:
        """(B, num_points, 3) keys of the samples at ``positions``, each drawn from its own stream
        (seed, epoch, dataset row) by `storage.resampling.gather_clouds` (a window of a version-4 refined
        cloud's stored order); an empty cloud stays at the zero key."""
        index = np.asarray(positions, dtype=np.int64).reshape(-1)
        starts = self.offsets[index]
        sizes = self.offsets[index + 1] - starts
        windowed = windowed_cloud(self.schema_version, self.source)
        return gather_clouds(self.keys.__getitem__, starts, sizes, self.rows[index], num_points, seed, epoch, windowed)

    def batch(self, positions: Rows, num_points: int, seed: int, epoch: int) -> SampleBatch[npt.NDArray[Any]]:
        """The samples at ``positions`` (0 to len - 1), each resampled to ``num_points`` from its
        own stream: the same arrays whatever the batch, its order or what else was loaded. Its
        ``index`` holds their dataset rows; cover fields are the caller's (osvp's `CoverBank`)."""
        index = np.asarray(positions, dtype=np.int64).reshape(-1)
        return SampleBatch(
            points=key_centres(self.resampled_keys(index, num_points, seed, epoch), self.voxel_size, self.grid_offset),
            view_state=self.view_state[index],
            label=self.labels[index],
            index=self.rows[index],
            **{name: values[index] for name, values in self.fields.items()},
            **({GRID_FIELD: self.grids.grids(index)} if self.grids is not None else {}),
        )


def load_memory(
    dataset: str | Dataset,
    source: Source = "points",
    *,
    rows: Rows | None = None,
    objects: Sequence[str] | None = None,
    covers: bool = True,
    fields: Sequence[str] = (),
    progress: Progress | None = None,
    storage_options: dict[str, Any] | None = None,
) -> MemoryDataset:
    """Read samples of ``dataset`` (a URL or an open `Dataset`) into memory, shard by shard.

        ``rows`` (dataset rows, held in that order) and ``objects`` (object ids or names) choose the
        samples; both given, the rows of those objects; neither, every sample. ``covers=False`` leaves a
        version-2 dataset's minimum covers unread; ``fields`` names optional sample fields to read too
    (``"grid"``: held as `CaseGrids`, built per batch). A damaged dataset is a `StorageError` naming the
        file and the fix (`storage.reader`).
    """
    check_source(source)
    found = dataset if isinstance(dataset, Dataset) else open_dataset(dataset, storage_options)
    chosen = found.chosen_rows(rows, objects)
    names = found.samples.shards
    shard_rows = found.samples.rows.astype(np.int64)
    owner = found.samples.codes[chosen]
    groups: dict[str, npt.NDArray[np.int64]] = {}
    if chosen.size:
        by_shard = np.argsort(owner, kind="stable")
        bounds = np.flatnonzero(np.diff(owner[by_shard])) + 1
        for positions in np.split(by_shard, bounds):
            groups[names[int(owner[positions[0]])]] = positions.astype(np.int64)

    total = chosen.size
    ambiguous = covers and found.has_ambiguity
    counts = np.zeros(total, dtype=np.int64)
    masks = np.zeros((total, 2), dtype=np.uint64)
    pieces: list[tuple[npt.NDArray[np.int64], npt.NDArray[np.int16]]] = []
    cover_pieces: list[tuple[npt.NDArray[np.int64], MaskArray, npt.NDArray[np.int64]]] = []
    universe_pieces: list[tuple[npt.NDArray[np.int64], MaskArray, npt.NDArray[np.int64]]] = []
    sample_fields = [f for f in fields_for(found.info.schema_version, fields) if f.name != GRID_FIELD]
    with_grids = GRID_FIELD in fields
    grid_cells: list[tuple[npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
    grid_task = np.zeros(total, dtype=np.int64)
    field_pieces: dict[str, list[tuple[npt.NDArray[np.int64], npt.NDArray[Any]]]] = {f.name: [] for f in sample_fields}
    done = 0
    for relative in sorted(groups):  # the reader's order: shards by path, samples in index order
        positions = groups[relative]
        local = shard_rows[chosen[positions]]
        shard = found.shard(relative)
        keys, sizes = _ragged_take(shard.array(keys_array(source)), shard.array(offsets_array(source)), local)
        counts[positions] = sizes
        pieces.append((positions, keys))
        masks[positions] = shard.array(MASKS)[local][:, [VIEW_STATE_COLUMN, LABEL_COLUMN]]
        these = ShardRows(source, local, shard.array)
        if with_grids:
            grid_task[positions] = len(grid_cells)
            grid_cells.append((np.asarray(shard.array(GRID_HITS)), np.asarray(shard.array(GRID_MISSES))))
        for sample_field in sample_fields:
            field_pieces[sample_field.name].append((positions, sample_field.read(these)))
        if ambiguous:
            listed, listed_sizes = _ragged_take(shard.array(COVERS), shard.array(offsets_array(COVERS)), local)
            cover_pieces.append((positions, listed, listed_sizes))
            cover_rows = np.asarray(shard.array(COVER_ROWS), dtype=np.uint64).reshape(-1)
            misses = (cover_rows[None, :] & masks[positions, VIEW_STATE_COLUMN][:, None]) == 0
            universe = np.broadcast_to(cover_rows, misses.shape)[misses]
            universe_pieces.append((positions, universe, misses.sum(axis=1, dtype=np.int64)))
        done += positions.size
        if progress is not None:
            progress(done, total)

    offsets = _offsets(counts)
    state_masks, label_masks = masks[:, VIEW_STATE_COLUMN].copy(), masks[:, LABEL_COLUMN].copy()
    packed_covers = None
    if ambiguous:
        columns = {name: found.values(name) for name in ("label_support", "min_covers", "min_covers_exact")}
        cover_masks, cover_offsets = _pack(cover_pieces, total, np.dtype(np.uint64))
        universe, universe_offsets = _pack(universe_pieces, total, np.dtype(np.uint64))
        packed_covers = PackedCovers(
            covers=cover_masks.astype(np.uint64, copy=False),
            cover_offsets=cover_offsets,
            universe=universe.astype(np.uint64, copy=False),
            universe_offsets=universe_offsets,
            support=columns["label_support"][chosen].astype(np.uint64),
            counts=columns["min_covers"][chosen].astype(np.int64),
            exact=columns["min_covers_exact"][chosen].astype(bool),
        )
    keys = _place(pieces, offsets, (3,), np.dtype(np.int16))
    held = _held(found, source, chosen, keys, offsets, state_masks, label_masks, packed_covers)
    grids = None
    if with_grids:
        hits = np.stack([h for h, _ in grid_cells]) if grid_cells else np.zeros((0, found.num_views, 0), np.uint8)
        misses = np.stack([m for _, m in grid_cells]) if grid_cells else hits
        grids = CaseGrids(hits=hits, misses=misses, task=grid_task, cases=state_masks)
    found_fields = {name: _in_order(found_pieces, total) for name, found_pieces in field_pieces.items()}
    return replace(held, fields=found_fields, grids=grids)


def load_index_facts(dataset: Dataset, source: Source = "points") -> MemoryDataset:
    """Every sample's index facts (object, view state, label) and none of its clouds or covers: what
    drawing a split or a training subset needs, for a dataset too large to hold (read from the
    index alone, no shard is opened)."""
    total = len(dataset)
    states = dataset.values("view_state").astype(np.uint64)
    labels = dataset.values("label").astype(np.uint64)
    chosen = np.arange(total, dtype=np.int64)
    empty = np.zeros((0, 3), dtype=np.int16)
    return _held(dataset, source, chosen, empty, np.zeros(total + 1, dtype=np.int64), states, labels, None)


def _held(
    found: Dataset,
    source: Source,
    chosen: npt.NDArray[np.int64],
    keys: npt.NDArray[np.int16],
    offsets: npt.NDArray[np.int64],
    state_masks: npt.NDArray[np.uint64],
    label_masks: npt.NDArray[np.uint64],
    covers: PackedCovers | None,
) -> MemoryDataset:
    """The `MemoryDataset` of rows ``chosen`` of ``found``: its identity from ``dataset.json``."""
    config = found.info.config
    width = found.num_views
    objects = pc.dictionary_encode(found.column("object_id")).combine_chunks()
    names = objects.dictionary.to_pylist()  # one string per object, shared by its samples
    codes = objects.indices.to_numpy(zero_copy_only=False)
    return MemoryDataset(
        url=found.url,
        config_hash=found.info.config_hash,
        schema_version=found.info.schema_version,
        num_views=width,
        voxel_size=float(config.voxel_size),
        grid_offset=np.asarray(config.grid_offset, dtype=np.float64),
        source=source,
        rows=chosen,
        keys=keys,
        offsets=offsets,
        view_state_masks=state_masks,
        label_masks=label_masks,
        view_state=bit_rows(state_masks, width),
        labels=bit_rows(label_masks, width),
        object_ids=tuple(names[code] for code in codes[chosen].tolist()),
        covers=covers,
    )


def _in_order(pieces: list[tuple[npt.NDArray[np.int64], npt.NDArray[Any]]], total: int) -> npt.NDArray[Any]:
    """One (total, ...) array of the pieces (positions, their values) in position order."""
    if not pieces:
        return np.zeros(0)
    first = pieces[0][1]
    placed = np.zeros((total, *first.shape[1:]), dtype=first.dtype)
    for positions, values in pieces:
        placed[positions] = values
    return placed


def _ragged_index(starts: npt.NDArray[np.int64], sizes: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Flat indices of the slices ``starts[i]:starts[i] + sizes[i]``, one after another."""
    total = int(sizes.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    begins = np.zeros(sizes.size, dtype=np.int64)
    np.cumsum(sizes[:-1], out=begins[1:])
    return np.repeat(starts - begins, sizes) + np.arange(total, dtype=np.int64)


def _ragged_take(
    values: npt.NDArray[Any], offsets: npt.NDArray[Any], rows: npt.NDArray[np.int64]
) -> tuple[npt.NDArray[Any], npt.NDArray[np.int64]]:
    """The slices ``values[offsets[r]:offsets[r + 1]]`` of ``rows``, concatenated, and their sizes."""
    bounds = np.asarray(offsets, dtype=np.int64)
    starts = bounds[rows]
    sizes = bounds[rows + 1] - starts
    if rows.size and np.array_equal(rows, np.arange(rows[0], rows[0] + rows.size)):
        return values[starts[0] : starts[0] + int(sizes.sum())], sizes  # a run of rows: one slice
    return values[_ragged_index(starts, sizes)], sizes


def _offsets(sizes: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    offsets = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    return offsets


def _place(
    pieces: list[tuple[npt.NDArray[np.int64], npt.NDArray[Any]]],
    offsets: npt.NDArray[np.int64],
    tail: tuple[int, ...],
    dtype: np.dtype[Any],
) -> npt.NDArray[Any]:
    """One array of the pieces (positions, their values packed) in position order."""
    if not pieces or offsets[-1] == 0:
        return np.zeros((0, *tail), dtype=dtype)
    read = np.concatenate([positions for positions, _ in pieces])
    if np.array_equal(read, np.arange(read.size)):  # read in position order (a whole load): one copy
        return np.concatenate([values for _, values in pieces]).astype(dtype, copy=False)
    packed = np.empty((int(offsets[-1]), *tail), dtype=dtype)
    for positions, values in pieces:
        sizes = offsets[positions + 1] - offsets[positions]
        packed[_ragged_index(offsets[positions], sizes)] = values
    return packed


def _pack(
    pieces: list[tuple[npt.NDArray[np.int64], npt.NDArray[Any], npt.NDArray[np.int64]]],
    total: int,
    dtype: np.dtype[Any],
) -> tuple[npt.NDArray[Any], npt.NDArray[np.int64]]:
    """(values, offsets) of the pieces (positions, values packed, sizes) in position order."""
    sizes = np.zeros(total, dtype=np.int64)
    for positions, _, found in pieces:
        sizes[positions] = found
    offsets = _offsets(sizes)
    return _place([(positions, values) for positions, values, _ in pieces], offsets, (), dtype), offsets
