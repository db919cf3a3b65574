"""Read a dataset from its URL: the index as a pyarrow Table, samples as numpy arrays.

A sample (``ds[i]``, `Dataset.sample`) is read through the field registry
(`storage.samples.SAMPLE_FIELDS`) and the one assembler (`storage.samples.hold_samples`), the path
every reader takes, so a registered field reaches it: each field as the row of a one-sample batch,
except the contract's own, which a sample shows as stored (`ITEM_FORMS`: the clouds whole, in metres;
the view sets as one bool per view).

Only committed tasks are visible. The merged ``index.parquet`` written by `finalise` is used when it
covers exactly the current commit records; otherwise the per-shard fragments are merged on open
(`storage.dataset.index`). A damaged file is never served: each shard is verified whole (every array, every
chunk file) the first time a dataset reads from it, and anything unreadable is a `StorageError`
naming the file and the fix.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from schemas.dataset import DatasetInfo
from schemas.index import CommitRecord, FailureRecord
from schemas.shard import COVER_ROWS, COVERAGE_GAINS, GAIN_TOTALS, GRID_HITS, GRID_MISSES, VIEW_GAINS
from storage.dataset.index import open_index
from storage.dataset.info import read_info
from storage.dataset.manifest import record_of
from storage.dataset.sample_index import SampleIndex, from_table, numpy_of
from storage.dataset.writer import committed_tasks, read_failures
from storage.samples.assemble import hold_samples
from storage.samples.batch import KeyArray, Source
from storage.samples.bits import mask_bits
from storage.samples.covers import cover_marginals, universe_rows
from storage.samples.gains import best_views
from storage.samples.held import Held, Ragged, Stacked
from storage.samples.occupancy_grid import case_grid
from storage.samples.resampling import key_centres
from storage.samples.sample_fields import SAMPLE_FIELDS, BatchFacts, Draw, ShardRows, fields_for
from storage.samples.splits import split_by_object
from storage.shards.groups import ShardReader
from storage.store.errors import check_store, is_store_failure, storage_failure
from storage.store.location import Location, StorageError, open_location

SHARD_CACHE = 16

Sample = dict[str, Any]
"""One sample by name: its fields, its id, its observed cloud and, with covers, their count."""

ItemForm = Callable[[Held, BatchFacts], Any]
"""How a sample shows a field from its held values (one sample's)."""


def _whole_cloud(held: Held, facts: BatchFacts) -> npt.NDArray[np.float32]:
    """The whole stored cloud, voxel centres in metres (float32): a batch draws ``num_points`` of it."""
    assert isinstance(held, Ragged)
    return key_centres(held.of(0), facts.voxel_size, facts.grid_offset)


def _view_bools(held: Held, facts: BatchFacts) -> npt.NDArray[np.bool_]:
    """A view set as one bool per view (a batch has 0/1 floats)."""
    assert isinstance(held, Stacked)
    return mask_bits(held.values[0], facts.num_views)


def _cover_bools(held: Held, facts: BatchFacts) -> npt.NDArray[np.bool_]:
    """(C, n) bool: the sample's listed minimum covers, unpadded (a batch pads them to its longest)."""
    assert isinstance(held, Ragged)
    return mask_bits(held.of(0), facts.num_views)


ITEM_FORMS: dict[str, ItemForm] = {
    "points": _whole_cloud,
    "view_state": _view_bools,
    "label": _view_bools,
    "support": _view_bools,
    "covers": _cover_bools,
}
"""The fields of the sample contract that a sample shows as stored rather than as the row of a
one-sample batch: its clouds whole, in metres, its view sets as bools per view. Every other field,
a plug-in's among them, is its batch row (`SampleField.finish` of one sample)."""

ITEM_ORDER = (
    "points",
    "observed",
    "view_state",
    "label",
    "support",
    "marginals",
    "covers",
    "min_covers",
    "min_covers_exact",
)
"""The keys a sample has always had, first and in this order (the other fields follow by name)."""

OBSERVED = "observed"
"""A sample's second cloud: the ``points`` field read from what its input views saw."""


def open_dataset(url: str, storage_options: dict[str, Any] | None = None) -> Dataset:
    """Open the dataset at a local path or fsspec URL for reading.

    Raises `StorageError` (one line naming the file and the fix) when ``dataset.json``, a commit
    record, an index file or a fragment is missing or damaged, or when the finalised index
    disagrees with the commit records.
    """
    location = open_location(url, storage_options)
    check_store(location)
    try:
        info = read_info(location)
        return Dataset(location, info, open_index(location))
    except StorageError:
        raise
    except Exception as exc:  # the store itself failed (damaged files are `DamagedFile`, named)
        if isinstance(exc, OSError) or is_store_failure(exc):
            raise storage_failure(url, exc) from None
        raise


class Dataset:
    """Random access to samples (``ds[i]``), filters, object-level splits, shuffled iteration."""

    def __init__(
        self,
        location: Location,
        info: DatasetInfo,
        index: SampleIndex | pa.Table,
        verified: set[str] | None = None,
    ) -> None:
        self.location = location
        self.info = info
        self.samples = index if isinstance(index, SampleIndex) else from_table(index)
        """Where each sample lives; its index columns, read on demand (`storage.dataset.sample_index`)."""
        self._shards: OrderedDict[str, ShardReader] = OrderedDict()
        self._verified: set[str] = set() if verified is None else verified
        """Shards verified by this reader (shared with its selections), so a shard evicted from the
        cache and opened again is not listed again."""
        self._columns: dict[str, npt.NDArray[Any]] = {}
        self._voxel = info.config.voxel_size
        self._offset = np.asarray(info.config.grid_offset, dtype=np.float64)

    # -- basics -------------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return self.location.url

    @property
    def num_views(self) -> int:
        return self.info.num_views

    def __len__(self) -> int:
        return len(self.samples)

    @property
    def index(self) -> pa.Table:
        """Every index column of every sample, in memory (read on first use; a large dataset's reader
        asks for the columns it needs instead: `column`)."""
        return self.samples.table()

    def column(self, name: str) -> pa.ChunkedArray:
        """One index column of every sample (read once)."""
        return self.samples.column(name)

    def index_row(self, i: int) -> dict[str, Any]:
        """Every index column of sample ``i`` (without reading the whole index)."""
        return self.samples.row(i)

    def values(self, name: str, keep: bool = True) -> npt.NDArray[Any]:
        """One index column of every sample as numpy (read and converted once; ``keep=False``: not kept,
        for a caller that reads a column of millions once)."""
        found = self._columns.get(name)
        if found is None and not keep:
            return numpy_of(self.samples.column(name, keep=False))
        return self._column(name)

    def counts(self, name: str) -> dict[Any, int]:
        """How many samples hold each value of an index column, sorted by value (read a row group at a
        time: a string column of millions is never held)."""
        return self.samples.counts(name)

    def task_table(self) -> pa.Table | None:
        """The dataset's tasks, one row each in sample order (`storage.dataset.manifest.TASKS_SCHEMA`: record,
        bytes, object), when a manifest names them; None for an index an earlier datagen finalised."""
        return self.samples.tasks

    def task_records(self) -> list[CommitRecord]:
        """Every committed task's record, sorted by task id: from the manifest when one names them (no
        read per task), else the commit records."""
        tasks = self.samples.tasks
        if tasks is None:
            return committed_tasks(self.location)
        return sorted((record_of(row) for row in tasks.to_pylist()), key=lambda r: r.task_id)

    def shard_of(self, i: int) -> str:
        """The shard sample ``i`` lives in."""
        return self.samples.shard(i)

    def row_of(self, i: int) -> int:
        """Its row there."""
        return int(self.samples.rows[i])

    def failures(self) -> list[FailureRecord]:
        return read_failures(self.location)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_shards"] = OrderedDict()  # shard handles are reopened lazily in each process
        return state

    # -- samples ------------------------------------------------------------------------------
    def shard(self, relative: str) -> ShardReader:
        reader = self._shards.get(relative)
        if reader is None:
            # verified whole before its first read, once per dataset and its selections
            span = self.samples.span(relative)
            reader = ShardReader(self.location, relative, verify=relative not in self._verified, span=span)
            self._verified.add(relative)
            self._shards[relative] = reader
            if len(self._shards) > SHARD_CACHE:
                self._shards.popitem(last=False)
        else:
            self._shards.move_to_end(relative)
        return reader

    def keys(self, i: int, source: Source = "points") -> npt.NDArray[np.int16]:
        """Integer keys (K, 3) of sample i's ``points`` or ``observed`` set, whole (as the ``points``
        field holds them)."""
        held = hold_samples([SAMPLE_FIELDS["points"]], self.shard_rows(i, source))["points"]
        assert isinstance(held, Ragged)
        return held.of(0)

    def resampled_keys(self, i: int, num_points: int, seed: int, epoch: int, source: Source = "points") -> KeyArray:
        """(num_points, 3) keys of sample i drawn from stream (seed, epoch, i) by the sample contract, as
        the ``points`` field draws them (`storage.samples.gather_clouds`): a version-4 refined cloud
        decodes only its window's chunks (`ShardReader.rows`, cached per shard), any other cloud is
        read whole."""
        rows = self.shard_rows(i, source, Draw(num_points, seed, epoch))
        held = hold_samples([SAMPLE_FIELDS["points"]], rows)["points"]
        assert isinstance(held, Stacked)
        return held.values[0]

    def centres(self, keys: npt.NDArray[np.integer]) -> npt.NDArray[np.float32]:
        """Voxel centres (float32 metres) of integer keys (`storage.samples.key_centres`)."""
        return key_centres(keys, self._voxel, self._offset)

    def masks(self, i: int) -> tuple[int, int]:
        """(view_state, label) of sample i as integer bit masks (as their fields hold them)."""
        held = hold_samples([SAMPLE_FIELDS["view_state"], SAMPLE_FIELDS["label"]], self.shard_rows(i))
        states, labels = held["view_state"], held["label"]
        assert isinstance(states, Stacked) and isinstance(labels, Stacked)
        return int(states.values[0]), int(labels.values[0])

    @property
    def has_ambiguity(self) -> bool:
        """Whether the samples carry their minimum covers (schema version 2 and later)."""
        return "label_support" in self.samples.column_names

    def ambiguity(self, i: int) -> LabelAmbiguity:
        """Sample i's minimum covers, their count and support, and U's set-cover rows."""
        if not self.has_ambiguity:
            raise StorageError(
                f"{self.url}: a version-{self.info.schema_version} dataset keeps no minimum covers; add them with "
                f"`datagen shards relabel {self.url} --out NEW_URL` (no re-imaging)"
            )
        shard = self.shard(self.shard_of(i))
        listed = hold_samples([SAMPLE_FIELDS["covers"]], self.shard_rows(i))["covers"]
        assert isinstance(listed, Ragged)
        view_state = self.masks(i)[0]
        return LabelAmbiguity(
            covers=listed.of(0),
            count=int(self._value(i, "min_covers")),
            exact=bool(self._value(i, "min_covers_exact")),
            support=int(self._value(i, "label_support")),
            universe_rows=universe_rows(shard.array(COVER_ROWS), view_state),
        )

    @property
    def has_next_view(self) -> bool:
        """Whether the samples carry the next-view labels and occupancy grids (schema version 3)."""
        return self.info.schema_version >= 3

    def next_view(self, i: int, grid: bool = False) -> NextView:
        """Sample i's gains, best next view and, with ``grid``, its occupancy grid (version 3)."""
        if not self.has_next_view:
            raise StorageError(
                f"{self.url}: a version-{self.info.schema_version} dataset keeps no next-view labels; add them with "
                f"`datagen shards relabel {self.url} --out NEW_URL` (no re-imaging)"
            )
        shard = self.shard(self.shard_of(i))
        row = self.row_of(i)
        gains = shard.array(VIEW_GAINS)[row]
        case = self.masks(i)[0]
        best, ties = best_views(gains[None, :], np.array([case], dtype=np.uint64), gains.shape[0])
        totals = shard.array(GAIN_TOTALS)
        return NextView(
            view_gains=gains,
            coverage_gains=shard.array(COVERAGE_GAINS)[row],
            visible_size=int(totals[0]),
            full_size=int(totals[1]),
            best_view=int(best[0]),
            best_view_ties=int(ties[0]),
            grid=case_grid(shard.array(GRID_HITS), shard.array(GRID_MISSES), case) if grid else None,
        )

    def _value(self, i: int, name: str) -> Any:
        """Index column ``name`` of sample ``i``: from the whole column when it was read already, else
        from its row group alone (one sample does not read a column of millions)."""
        found = self._columns.get(name)
        return found[i] if found is not None else self.samples.value(i, name)

    def _column(self, name: str) -> npt.NDArray[Any]:
        """An index column as numpy, converted once per reader."""
        found = self._columns.get(name)
        if found is None:
            found = self._columns[name] = numpy_of(self.samples.column(name, keep=False))
        return found

    def __getitem__(self, i: int) -> Sample:
        """Sample ``i`` (`sample`): its clouds (float32 metres, whole), view state and label (bool per
        view) and id; with version-2 labels also ``support`` (bool), ``marginals`` (float32, the
        fraction of the listed minimum covers holding each view), ``covers`` (bool, one row per listed
        cover) and ``min_covers`` with ``min_covers_exact``; and every other registered field the
        dataset has (``index``, ``cloud_size``, a version-3 dataset's gains and best view, a
        plug-in's), as the row of a one-sample batch."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample {i} out of range for {len(self)} samples")
        return self.sample(i % len(self))

    def sample(self, i: int, fields: Sequence[str] | None = None) -> Sample:
        """Sample ``i`` read through the field registry and the one assembler: every field the dataset
        has (``fields`` None: what ``ds[i]`` gives, the listed covers among them where kept), or only
        those ``fields`` names (``"observed"``: the cloud the input views saw). A field the registry
        lacks, or that this dataset does not keep, is a `ValueError` (`storage.samples.fields_for`)."""
        names = None if fields is None else set(fields)
        asked = ("covers",) if fields is None and self.has_ambiguity else [n for n in names or () if n != OBSERVED]
        chosen = [
            field
            for field in fields_for(self.info.schema_version, asked, has_covers=self.has_ambiguity)
            if names is None or field.name in names
        ]
        rows = self.shard_rows(i)
        facts = self.batch_facts(rows)
        held = hold_samples(chosen, rows)
        found: Sample = {}
        for field in chosen:
            form = ITEM_FORMS.get(field.name)
            values = held[field.name]
            found[field.name] = form(values, facts) if form else field.finish(values, _FIRST, facts)[0]
        if names is None or OBSERVED in names:
            observed = hold_samples([SAMPLE_FIELDS["points"]], self.shard_rows(i, "observed"))["points"]
            found[OBSERVED] = _whole_cloud(observed, facts)
        if fields is None and self.has_ambiguity:
            found["min_covers"] = int(self._value(i, "min_covers"))
            found["min_covers_exact"] = bool(self._value(i, "min_covers_exact"))
        first = {name: found.pop(name) for name in ITEM_ORDER if name in found}
        return {"sample_id": self.samples.value(i, "sample_id"), **first, **found}

    def shard_rows(
        self, i: int, source: Source = "points", draw: Draw | None = None, whole_columns: bool = False
    ) -> ShardRows:
        """Sample ``i``'s row of its shard as a registered field reads it (`storage.samples.ShardRows`):
        clouds of ``source``, held whole or, with ``draw``, drawn now; its index columns from their
        row groups, or with ``whole_columns`` from whole columns read once (a reader of every sample)."""
        shard = self.shard(self.shard_of(i))
        rows = np.array([i], dtype=np.int64)

        def column(name: str) -> npt.NDArray[Any]:
            return self.values(name)[rows] if whole_columns else np.asarray([self._value(i, name)])

        return ShardRows(
            source=source,
            local=np.array([self.row_of(i)], dtype=np.int64),
            array=shard.array,
            rows=rows,
            schema_version=self.info.schema_version,
            num_views=self.num_views,
            column=column,
            taker=lambda name: shard.rows(name).take,
            draw=draw,
        )

    def batch_facts(self, rows: ShardRows) -> BatchFacts:
        """What finishing the batch of ``rows`` (`shard_rows`) needs (`storage.samples.BatchFacts`)."""
        return BatchFacts(
            num_views=self.num_views,
            voxel_size=float(self.info.config.voxel_size),
            grid_offset=self._offset,
            schema_version=self.info.schema_version,
            source=rows.source,
            rows=rows.dataset_rows,
            draw=rows.draw,
        )

    # -- selections ---------------------------------------------------------------------------
    def chosen_rows(
        self, rows: npt.ArrayLike | None = None, objects: Sequence[str] | str | None = None
    ) -> npt.NDArray[np.int64]:
        """The rows a reader holds, in order: ``rows`` (each once; all rows when None), kept where
        their object (id or name) is among ``objects`` (when given). Every reader chooses through
        this: an out-of-range row is an `IndexError`, a repeated one a `ValueError`."""
        total = len(self)
        if rows is None:
            chosen = np.arange(total, dtype=np.int64)
        else:
            chosen = np.asarray(rows, dtype=np.int64).reshape(-1)
            if chosen.size and (chosen.min() < 0 or chosen.max() >= total):
                raise IndexError(f"rows must lie in 0 to {total - 1} ({self.url} holds {total} samples)")
            if np.unique(chosen).size != chosen.size:
                raise ValueError("rows repeat a sample (a row given more than once); give each dataset row once")
        if objects is not None:
            chosen = chosen[self._of_objects(objects)[chosen]]
        return chosen

    def _of_objects(self, objects: Sequence[str] | str) -> npt.NDArray[np.bool_]:
        """Per sample: whether its object's id or name is among ``objects``."""
        wanted = pa.array([objects] if isinstance(objects, str) else list(objects), pa.string())
        keep = pc.or_(
            pc.is_in(self.samples.column("object_name"), wanted), pc.is_in(self.samples.column("object_id"), wanted)
        )
        return np.asarray(keep.to_numpy(zero_copy_only=False), dtype=bool)

    def select(self, rows: npt.ArrayLike) -> Dataset:
        """A dataset over a subset of index rows (in the given order)."""
        return Dataset(self.location, self.info, self.samples.select(rows), self._verified)

    def filter(
        self,
        objects: Sequence[str] | str | None = None,
        rotations: Sequence[int] | int | None = None,
        case_sizes: Sequence[int] | int | None = None,
    ) -> Dataset:
        """Samples whose object (name or id), rotation and case size are among those given."""
        keep = np.ones(len(self), dtype=bool)
        if objects is not None:
            keep &= self._of_objects(objects)
        if rotations is not None:
            wanted_r = [int(rotations)] if isinstance(rotations, (int, np.integer)) else [int(r) for r in rotations]
            keep &= np.isin(self._column("rotation"), wanted_r)
        if case_sizes is not None:
            wanted_c = [int(case_sizes)] if isinstance(case_sizes, (int, np.integer)) else [int(c) for c in case_sizes]
            keep &= np.isin(self._column("case_size"), wanted_c)
        return self.select(np.flatnonzero(keep))

    def object_ids(self) -> list[str]:
        return sorted(pc.unique(self.samples.column("object_id")).to_pylist())

    def split(self, val: float = 0.2, seed: int = 0) -> tuple[Dataset, Dataset]:
        """(train, val) by object, never by sample: every sample of an object lands on one side.

        ``round(val * objects)`` objects are held out, and at least one whenever ``val`` > 0 (before,
        a small fraction of few objects rounded to none); the draw is `storage.samples.split_by_object`'s,
        the one osvp's object split makes. A ``val`` outside [0, 1] is a `storage.samples.SplitError`
        (a ValueError).
        """
        train, held = split_by_object(self.samples.column("object_id").to_pylist(), val, seed)
        return self.select(train), self.select(held)

    # -- iteration ----------------------------------------------------------------------------
    def shard_blocks(self) -> list[npt.NDArray[np.int64]]:
        """Sample indices grouped by shard (shards sorted by path, rows in index order)."""
        return self.samples.by_shard()

    def shuffled_order(self, seed: int, epoch: int = 0, shards_mixed: int = 4) -> npt.NDArray[np.int64]:
        """A shard-aware shuffle: shards in random order, taken ``shards_mixed`` at a time, their
        samples shuffled together. Only that many shards are needed at once (the reader caches
        `SHARD_CACHE`), which is what keeps shuffled reading fast; a larger value mixes more."""
        if shards_mixed < 1:
            raise ValueError(f"shards_mixed = {shards_mixed} must be >= 1")
        rng = np.random.default_rng(np.random.SeedSequence([seed, epoch]))
        blocks = self.shard_blocks()
        shard_order = rng.permutation(len(blocks))
        order: list[npt.NDArray[np.int64]] = []
        for start in range(0, len(blocks), shards_mixed):
            group = np.concatenate([blocks[b] for b in shard_order[start : start + shards_mixed]])
            order.append(rng.permutation(group))
        return np.concatenate(order) if order else np.empty(0, dtype=np.int64)

    def iter_shuffled(self, seed: int = 0, epoch: int = 0, shards_mixed: int = 4) -> Iterator[Sample]:
        for i in self.shuffled_order(seed, epoch, shards_mixed):
            yield self[int(i)]


@dataclass(frozen=True)
class LabelAmbiguity:
    """How many view sets are as good as a sample's label (schema version 2)."""

    covers: npt.NDArray[np.uint64]
    """The minimum covers listed (masks, sorted as tuples of views; all of them when ``exact``)."""
    count: int
    """How many minimum covers exist; a lower bound unless ``exact``."""
    exact: bool
    support: int
    """Mask of the views in at least one minimum cover (always exact)."""
    universe_rows: npt.NDArray[np.uint64]
    """U's set-cover rows: a view set covers U exactly when it meets each of them."""

    def marginals(self, num_views: int) -> npt.NDArray[np.float64]:
        """Per view, the fraction of the listed minimum covers holding it."""
        return cover_marginals(self.covers, num_views)

    def covers_universe(self, views: int) -> bool:
        """Whether the view set ``views`` (a mask) covers U."""
        return bool(((self.universe_rows & np.uint64(views)) != 0).all())


@dataclass(frozen=True)
class NextView:
    """What the next-best-view planners learn from one sample (schema version 3)."""

    view_gains: npt.NDArray[np.uint32]
    """(n,) keys of each view's visibility set that the case has not seen."""
    coverage_gains: npt.NDArray[np.uint32]
    """(n,) keys of P_full each view would add to the case's coverage."""
    visible_size: int
    """Keys any view sees: the visibility gains' denominator."""
    full_size: int
    """|P_full|: the coverage gains' denominator."""
    best_view: int
    """The largest visibility gain outside the case, lowest index first; -1 for a case of every view."""
    best_view_ties: int
    grid: npt.NDArray[np.float32] | None
    """(32, 32, 32) occupancy probabilities [x, y, z] when asked for."""


_FIRST = np.zeros(1, dtype=np.int64)
"""The one sample of a one-sample batch."""


def mask_to_bools(mask: int, width: int) -> npt.NDArray[np.bool_]:
    """One bool per view of a mask (bit v = view v): `storage.samples.mask_bits`."""
    return mask_bits(mask, width)
