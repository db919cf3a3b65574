"""A dataset's samples in memory: read once, shard by shard, then batched without a reader.

A training epoch over a few thousand samples must not wait on Zarr reads, so `load_memory` reads
the integer keys of the chosen samples once (whole shard arrays, the reader's fast order) and keeps
them packed in one int16 array with offsets, with each sample's view state and label (as masks and
as 0/1 rows), object id, the dataset's voxel size, grid offset, schema version and stored config
hash, and, for a version-2 dataset, its minimum covers and U's set-cover rows packed as uint64 masks
with offsets. `MemoryDataset.batch` then builds fixed-size point clouds by a numpy gather. Asked for
the occupancy grids (``fields=("grid",)``), it keeps each task's per-view ray cells once (`CaseGrids`,
a few hundred bytes a sample) and builds a batch's grids when asked, instead of 128 KB per sample.

Every field is read and batched by `storage.samples.assemble` (the registry `storage.samples.sample_fields`), the path
the stream and the map-style reader take, and follows the sample contract (`storage.samples.resampling`):
a sample held at position ``p`` is resampled from stream ``(seed, epoch, rows[p])``, its row in the
dataset it was loaded from, so a side loaded alone (``rows=`` or ``objects=``) gives exactly the
tensors it gives in a whole load, and a whole load exactly what `storage.torch.OSVPDataset` gives
for the same (seed, epoch, index).

A version-4 dataset's refined clouds are drawn as windows of their stored order (`storage.samples.resampling`);
memory still holds each whole cloud, since every epoch draws another window of it.

Depends on numpy and `storage` only: no torch here (osvp wraps the arrays as tensors).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow.compute as pc

from schemas.shard import COVER_ROWS, MASKS, VIEW_STATE_COLUMN
from storage.readers.reader import Dataset, open_dataset
from storage.samples.assemble import HeldSamples, finish_batch, hold_samples, place_samples
from storage.samples.batch import SampleBatch, Source, check_source
from storage.samples.bits import bit_rows
from storage.samples.held import Positions, Ragged, Stacked
from storage.samples.resampling import gather_clouds, windowed_cloud
from storage.samples.sample_fields import (
    CORE_FIELDS,
    COVER_FIELDS,
    SAMPLE_FIELDS,
    BatchFacts,
    CaseGrids,
    Draw,
    SampleField,
    ShardRows,
    fields_for,
    stacked_values,
)

Progress = Callable[[int, int], None]
"""Called with (samples read, samples to read) after each shard."""
MaskArray = npt.NDArray[np.uint64]
Rows = Sequence[int] | npt.NDArray[np.integer]

__all__ = ["CaseGrids", "MemoryDataset", "PackedCovers", "load_index_facts", "load_memory"]


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
    object_ids: tuple[str, ...]
    held: HeldSamples
    """Every held field's values (`storage.samples.sample_fields`), by name, in position order."""
    sample_fields: tuple[SampleField, ...]
    """The fields held, in `storage.samples.fields_for`'s order."""
    asked: tuple[str, ...] = ()
    """The optional fields the load was asked for: every batch has them."""
    covers: PackedCovers | None = None
    """None for a version-1 dataset, or when the load was asked to leave them out."""
    facts_only: bool = False
    """Held from the index alone (`load_index_facts`): no clouds."""

    def __len__(self) -> int:
        return int(self.rows.size)

    # -- what osvp and the tests read of the held fields ----------------------------------------
    @property
    def rows(self) -> npt.NDArray[np.int64]:
        """(S,) the dataset row of each held sample: its resampling stream."""
        return self._stacked("index")

    @property
    def keys(self) -> npt.NDArray[np.int16]:
        """(K, 3) every held sample's keys, packed in position order."""
        return self._clouds.values

    @property
    def offsets(self) -> npt.NDArray[np.int64]:
        """(S + 1,) sample ``p``'s keys are ``keys[offsets[p]:offsets[p + 1]]``."""
        return self._clouds.offsets

    @property
    def view_state_masks(self) -> MaskArray:
        return self._stacked("view_state")

    @property
    def label_masks(self) -> MaskArray:
        return self._stacked("label")

    @cached_property
    def view_state(self) -> npt.NDArray[np.float32]:
        """(S, n) 0/1 rows of the view-state masks (bit v = view v)."""
        return bit_rows(self.view_state_masks, self.num_views)

    @cached_property
    def labels(self) -> npt.NDArray[np.float32]:
        """(S, n) 0/1 rows of the label masks."""
        return bit_rows(self.label_masks, self.num_views)

    @property
    def fields(self) -> dict[str, npt.NDArray[Any]]:
        """(S, ...) values of every held field batched as held (``cloud_size``, the version-3 gains
        and best view, a plug-in's), by name."""
        return {
            f.name: self._stacked(f.name)
            for f in self.sample_fields
            if f.name not in CORE_FIELDS and f.finish is stacked_values and isinstance(self.held[f.name], Stacked)
        }

    @property
    def grids(self) -> CaseGrids | None:
        """The occupancy grids' ray cells when the load asked for them; a batch then carries ``grid``."""
        found = self.held.get("grid")
        return found if isinstance(found, CaseGrids) else None

    def _stacked(self, name: str) -> npt.NDArray[Any]:
        found = self.held[name]
        assert isinstance(found, Stacked)
        return found.values

    @property
    def _clouds(self) -> Ragged:
        found = self.held["points"]
        assert isinstance(found, Ragged)
        return found

    def keys_of(self, position: int) -> npt.NDArray[np.int16]:
        """The integer keys (K, 3) of the sample held at ``position``."""
        return self._clouds.of(position)

    def resampled_keys(self, positions: Rows, num_points: int, seed: int, epoch: int) -> npt.NDArray[np.int16]:
        """(B, num_points, 3) keys of the samples at ``positions``, each drawn from its own stream
        (seed, epoch, dataset row) by `storage.samples.gather_clouds` (a window of a version-4 refined
        cloud's stored order); an empty cloud stays at the zero key."""
        index = np.asarray(positions, dtype=np.int64).reshape(-1)
        starts = self.offsets[index]
        sizes = self.offsets[index + 1] - starts
        windowed = windowed_cloud(self.schema_version, self.source)
        return gather_clouds(self.keys.__getitem__, starts, sizes, self.rows[index], num_points, seed, epoch, windowed)

    def batch(
        self, positions: Rows, num_points: int, seed: int, epoch: int, covers: bool = False
    ) -> SampleBatch[npt.NDArray[Any]]:
        """The samples at ``positions`` (0 to len - 1), each resampled to ``num_points`` from its
        own stream: the same arrays whatever the batch, its order or what else was loaded. Its
        ``index`` holds their dataset rows; ``covers``: with the listed covers padded to the batch's
        longest listing (``covers``, ``cover_mask``), when held."""
        if self.facts_only:
            raise ValueError("samples held from the index alone (load_index_facts) have no clouds to batch")
        index = np.asarray(positions, dtype=np.int64).reshape(-1)
        chosen = [f for f in self.sample_fields if not f.optional or f.name in self.asked or (covers and f.covers)]
        facts = BatchFacts(
            num_views=self.num_views,
            voxel_size=self.voxel_size,
            grid_offset=self.grid_offset,
            schema_version=self.schema_version,
            source=self.source,
            rows=self.rows[index],
            draw=Draw(num_points, seed, epoch),
        )
        return finish_batch(chosen, self.held, index, facts)


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
    (``"grid"``: held as ray cells, built per batch). A damaged dataset is a `StorageError` naming the
    file and the fix (`storage.readers.reader`).
    """
    check_source(source)
    found = dataset if isinstance(dataset, Dataset) else open_dataset(dataset, storage_options)
    chosen = found.chosen_rows(rows, objects)
    ambiguous = covers and found.has_ambiguity
    asked = [*fields, *(name for name in COVER_FIELDS if ambiguous and name not in fields)]
    sample_fields = fields_for(found.info.schema_version, asked, has_covers=ambiguous)
    columns = {name: found.values(name) for f in sample_fields for name in f.columns}
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
    pieces: list[tuple[Positions, HeldSamples]] = []
    universe_pieces: list[tuple[Positions, Ragged]] = []
    done = 0
    for relative in sorted(groups):  # the reader's order: shards by path, samples in index order
        positions = groups[relative]
        these = chosen[positions]
        local = shard_rows[these]
        shard = found.shard(relative)
        read = ShardRows(
            source=source,
            local=local,
            array=shard.array,
            rows=these,
            schema_version=found.info.schema_version,
            num_views=found.num_views,
            column=lambda name, these=these: columns[name][these],  # type: ignore[misc]
        )
        pieces.append((positions, hold_samples(sample_fields, read)))
        if ambiguous:
            universe_pieces.append((positions, _universe(shard.array(COVER_ROWS), shard.array(MASKS), local)))
        done += positions.size
        if progress is not None:
            progress(done, total)

    if pieces:
        held, kept = place_samples(pieces, total), tuple(sample_fields)
    else:
        held, kept = _empty(sample_fields, found, source, columns)
    packed = _packed_covers(found, chosen, held, universe_pieces, total) if ambiguous and "covers" in held else None
    return replace(_memory(found, source, chosen, held, kept, packed), asked=tuple(fields))


def _universe(cover_rows: npt.NDArray[Any], masks: npt.NDArray[Any], local: Positions) -> Ragged:
    """Each sample's U rows the view state leaves: what `CoverBank` judges a prediction against."""
    rows = np.asarray(cover_rows, dtype=np.uint64).reshape(-1)
    states = np.asarray(masks, dtype=np.uint64)[local, VIEW_STATE_COLUMN]
    misses = (rows[None, :] & states[:, None]) == 0
    universe = np.broadcast_to(rows, misses.shape)[misses]
    sizes = misses.sum(axis=1, dtype=np.int64)
    offsets = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    return Ragged(universe, offsets)


def _packed_covers(
    found: Dataset,
    chosen: npt.NDArray[np.int64],
    held: HeldSamples,
    universe_pieces: list[tuple[Positions, Ragged]],
    total: int,
) -> PackedCovers:
    listed = held["covers"]
    assert isinstance(listed, Ragged)
    universe = (
        Ragged.placed(universe_pieces, total)
        if universe_pieces
        else Ragged(np.zeros(0, np.uint64), np.zeros(total + 1, np.int64))
    )
    support = held["support"]
    assert isinstance(support, Stacked)
    return PackedCovers(
        covers=listed.values.astype(np.uint64, copy=False),
        cover_offsets=listed.offsets,
        universe=universe.values.astype(np.uint64, copy=False),
        universe_offsets=universe.offsets,
        support=support.values.astype(np.uint64),
        counts=found.values("min_covers")[chosen].astype(np.int64),
        exact=found.values("min_covers_exact")[chosen].astype(bool),
    )


def _empty(
    sample_fields: Sequence[SampleField], found: Dataset, source: Source, columns: dict[str, npt.NDArray[Any]]
) -> tuple[HeldSamples, tuple[SampleField, ...]]:
    """No samples chosen: every field held from no row of a shard (so of its dtype and shape); a
    dataset with no shard at all holds the core fields, empty."""
    names = found.samples.shards
    if not names:
        return _core_facts(np.zeros(0, np.int64), np.zeros(0, np.uint64), np.zeros(0, np.uint64))
    none = np.zeros(0, dtype=np.int64)
    read = ShardRows(
        source=source,
        local=none,
        array=found.shard(sorted(names)[0]).array,
        rows=none,
        schema_version=found.info.schema_version,
        num_views=found.num_views,
        column=lambda name: columns[name][none],
    )
    return hold_samples(sample_fields, read), tuple(sample_fields)


def _core_facts(
    rows: npt.NDArray[np.int64], states: npt.NDArray[np.uint64], labels: npt.NDArray[np.uint64]
) -> tuple[HeldSamples, tuple[SampleField, ...]]:
    """The core fields without clouds: rows, view states and labels."""
    held: HeldSamples = {
        "index": Stacked(rows),
        "view_state": Stacked(states),
        "label": Stacked(labels),
        "points": Ragged(np.zeros((0, 3), dtype=np.int16), np.zeros(rows.size + 1, dtype=np.int64)),
    }
    return held, tuple(SAMPLE_FIELDS[name] for name in sorted(held))


def load_index_facts(dataset: Dataset, source: Source = "points") -> MemoryDataset:
    """Every sample's index facts (object, view state, label) and none of its clouds or covers: what
    drawing a split or a training subset needs, for a dataset too large to hold (read from the
    index alone, no shard is opened)."""
    chosen = np.arange(len(dataset), dtype=np.int64)
    states, labels = dataset.values("view_state").astype(np.uint64), dataset.values("label").astype(np.uint64)
    held, core = _core_facts(chosen, states, labels)
    return _memory(dataset, source, chosen, held, core, None, facts_only=True)


def _memory(
    found: Dataset,
    source: Source,
    chosen: npt.NDArray[np.int64],
    held: HeldSamples,
    sample_fields: tuple[SampleField, ...],
    covers: PackedCovers | None,
    facts_only: bool = False,
) -> MemoryDataset:
    """The `MemoryDataset` of rows ``chosen`` of ``found``: its identity from ``dataset.json``."""
    config = found.info.config
    objects = pc.dictionary_encode(found.column("object_id")).combine_chunks()
    names = objects.dictionary.to_pylist()  # one string per object, shared by its samples
    codes = objects.indices.to_numpy(zero_copy_only=False)
    return MemoryDataset(
        url=found.url,
        config_hash=found.info.config_hash,
        schema_version=found.info.schema_version,
        num_views=found.num_views,
        voxel_size=float(config.voxel_size),
        grid_offset=np.asarray(config.grid_offset, dtype=np.float64),
        source=source,
        object_ids=tuple(names[code] for code in codes[chosen].tolist()),
        held=held,
        sample_fields=sample_fields,
        covers=covers,
        facts_only=facts_only,
    )
