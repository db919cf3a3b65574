"""Streaming reads for PyTorch: `ShardStream`, an ``IterableDataset`` of ready batches that reads each
shard whole, once per epoch, so a dataset larger than memory trains at the speed of its shards.
Importing `storage` never imports torch; importing this module does (as `storage.torch`).

One epoch, for a given (seed, epoch, worker count, world size):

1. the selected shards (every shard holding a selected row) are permuted with stream
   ``(seed, epoch, STREAM_TAG, 1)``; in that order each shard goes to the *part* holding the fewest
   selected samples so far (ties: the lowest part). There are ``world_size * num_workers`` parts;
   rank ``r``'s DataLoader worker ``w`` is part ``r * num_workers + w``;
2. a part reads its shards in order, whole, up to ``read_ahead`` shards ahead in background threads:
   `storage.ShardReader` verifies each shard first (every array and chunk file there), then each
   array is one read, decoded by `whole_array` (CRC32C checked) or, failing that, read by
   `ShardReader.array`; so damage is the same named `storage.StorageError` as the map-style reader's;
3. its samples pass a shuffle buffer of ``shuffle_buffer`` samples (each shard's rows permuted on the
   way in; stream ``(seed, epoch, STREAM_TAG, 2, part + 1)``); the order out of the buffer is
   computed from the index alone before any read, which is what makes `skip` cheap and exact;
4. each cloud is resampled from stream (seed, epoch, dataset row index) as it is read, so a sample's
   tensors equal those of the in-memory path (`osvp.data.SampleBank`) and of
   `storage.torch.OSVPDataset` for the same seed, epoch and row, whatever the order: a cloud of
   version 1 to 3 by `storage.resample_many_keys` (`resample_keys`'s arrays, a shard's streams
   seeded together); a version-4 refined cloud by `storage.gather_clouds`, one window of its
   stored order, decoding only the key chunks that hold the shard's windows (`storage.shards.RowTaker`),
   not the whole clouds;
5. the part yields batches of ``batch_size`` samples (its last one smaller unless ``drop_last``), the
   tensors of a batch all views of one storage, made in shared memory in a worker: the DataLoader
   sends one shared-memory segment a batch instead of one a tensor.

Every selected sample is yielded exactly once per epoch across workers and ranks (``drop_last=False``).
With ``drop_last=True`` every part yields the same number of full batches (the smallest part's), so
every rank yields as many batches as every other: what DistributedDataParallel needs; the samples left
out are at most about one shard per part.

Memory holds the shuffle buffer (resampled clouds: ``shuffle_buffer * num_points * 6`` bytes), the
shards in flight (``read_ahead`` + 1, decoded) and the batches the DataLoader queues, never the clouds
of the dataset: what grows with it is the index (about 1 KB a sample while the dataset is open, and a
few bytes a selected row after).

Resuming mid-epoch: a DataLoader (``batch_size=None``, the default ``in_order=True``) takes batches
from its workers in turn, 0, 1, ..., skipping a worker once it is exhausted. ``skip = K`` counts
batches *the DataLoader* yielded in this epoch; each worker works out from the parts' batch counts
how many of those K were its own (round robin, as the DataLoader does) and starts after them, reading
only the shards that still hold samples to yield. A new DataLoader starts its turns at worker 0, so
the worker whose turn came next after K plays worker 0: worker ``w`` of the new DataLoader plays
``(next + w) % num_workers``. So a run restarted with ``skip = K`` (or `load_state_dict` of
``state_dict(consumed=K)``) yields exactly the batches an uninterrupted run yielded after its K-th,
given the same worker count and world size.
"""

from __future__ import annotations

import itertools
import math
import os
import queue
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
import zarr
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from storage.readers.reader import Dataset, open_dataset
from storage.samples.assemble import HeldSamples, finish_arrays, hold_samples, place_samples, take_samples
from storage.samples.batch import SampleBatch, Source, check_source
from storage.samples.resampling import windowed_cloud
from storage.samples.sample_fields import COVER_FIELDS, BatchFacts, Draw, ShardRows, fields_for
from storage.shards.codec import RowTaker, whole_array
from storage.shards.groups import ShardReader
from storage.store.location import Location, open_location

WORKER_ZARR_CONFIG = {"codec_pipeline.batch_size": 64, "threading.max_workers": 1}
"""zarr settings of a DataLoader worker (a process of the stream's own): what zarr still reads there
(group metadata, and arrays `whole_array` leaves to it) in one thread, a shard's chunks in one batch.
The main process (``num_workers=0``) keeps zarr's defaults."""

STREAM_TAG = 0x57EA4
"""Tag of the stream's own random streams (shard order, shuffle buffer), apart from the resampling
streams (seed, epoch, index)."""

Batch = SampleBatch[torch.Tensor]


_Prepared = tuple[HeldSamples, int]
"""A sample as read and drawn, waiting in the shuffle buffer: its shard's held values and its slot there."""


@dataclass(frozen=True)
class _Part:
    """What one part (one worker of one rank) reads and yields in an epoch."""

    shards: list[int]
    """Indices into the stream's shard list, in read order."""
    order: npt.NDArray[np.int64]
    """Dataset rows in the order they leave the shuffle buffer (already cut for ``drop_last``)."""


class ShardStream(IterableDataset[Batch]):
    """Batches of whole-shard reads, each a `storage.SampleBatch` of tensors: ``points``,
    ``view_state``, ``label`` and ``index`` (dataset rows); for a version-2 dataset also ``marginals``
    and ``support``, and with ``covers=True`` the listed minimum covers padded to the batch's largest
    listing (``covers``, ``cover_mask``); every registered sample field the dataset has (version 3:
    ``view_gain``, ``coverage_gain``, ``best_view``), and the optional ones ``fields`` names (``grid``).

    Use it with ``DataLoader(stream, batch_size=None, num_workers=W)`` (`loader` builds one): the
    batches are made in the workers, so the DataLoader has nothing to collate. ``rows`` (dataset row
    indices) and ``objects`` (ids or names) select samples; a split by object selects whole shards.
    ``rank`` and ``world_size`` default to torch.distributed's when it is initialised, else 0 and 1.
    ``num_workers``, when given, is checked against the DataLoader's and lets `len` say how many
    batches this rank yields.
    """

    def __init__(
        self,
        data: str | Dataset,
        *,
        num_points: int = 2048,
        batch_size: int = 32,
        source: Source = "points",
        seed: int = 0,
        epoch: int = 0,
        rows: npt.ArrayLike | None = None,
        objects: Sequence[str] | None = None,
        shuffle_buffer: int = 4096,
        read_ahead: int = 2,
        drop_last: bool = False,
        covers: bool = False,
        fields: Sequence[str] = (),
        rank: int | None = None,
        world_size: int | None = None,
        num_workers: int | None = None,
        skip: int = 0,
        storage_options: dict[str, Any] | None = None,
    ) -> None:
        check_source(source)
        for name, value, least in (
            ("num_points", num_points, 1),
            ("batch_size", batch_size, 1),
            ("shuffle_buffer", shuffle_buffer, 1),
            ("read_ahead", read_ahead, 1),
            ("skip", skip, 0),
        ):
            if value < least:
                raise ValueError(f"{name} = {value} must be >= {least}")
        if num_workers is not None and num_workers < 0:
            raise ValueError(f"num_workers = {num_workers} must be >= 0")
        dataset = data if isinstance(data, Dataset) else open_dataset(data, storage_options)
        self.url = dataset.url
        self.storage_options = dict(dataset.location.storage_options)
        self._location: Location | None = dataset.location
        self._pid = os.getpid()
        self.num_views = dataset.num_views
        self.voxel_size = float(dataset.info.config.voxel_size)
        self.grid_offset = np.asarray(dataset.info.config.grid_offset, dtype=np.float64)
        self.ambiguous = dataset.has_ambiguity
        self.windowed = windowed_cloud(dataset.info.schema_version, source)
        """Clouds read by windows of their stored order (`storage.cloud_positions`)."""
        if covers and not self.ambiguous:
            raise ValueError(
                f"{self.url}: covers=True needs a dataset with minimum covers (version 2); this one is version "
                f"{dataset.info.schema_version}"
            )
        asked = [*fields, *(COVER_FIELDS if covers else ())]
        self.sample_fields = fields_for(dataset.info.schema_version, asked, has_covers=self.ambiguous)
        """The registered `storage.samples.SampleField`s it reads and batches."""
        self.field_names = [field.name for field in self.sample_fields]
        self.schema_version = dataset.info.schema_version
        self._columns = {name: dataset.values(name) for f in self.sample_fields for name in f.columns}
        """The index columns the fields read, per dataset row."""
        self.num_points = num_points
        self.batch_size = batch_size
        self.source = source
        self.seed = seed
        self.epoch = epoch
        self.skip = skip
        self.shuffle_buffer = shuffle_buffer
        self.read_ahead = read_ahead
        self.drop_last = drop_last
        self.covers = covers
        self.num_workers = num_workers
        self.rank, self.world_size = _distributed(rank, world_size)
        self._select(dataset, rows, objects)

    def _select(self, dataset: Dataset, rows: npt.ArrayLike | None, objects: Sequence[str] | None) -> None:
        """Group the selected dataset rows by shard (shards sorted by path, rows ascending). Every row of
        a dataset whose shards' rows lie together (as the manifest numbers them) is grouped without a
        sort or a copy of a per-row array: at six million samples each such array is 24-48 MB."""
        total = len(dataset)
        names = dataset.samples.shards
        codes = dataset.samples.codes
        everything = rows is None and objects is None
        if everything and (codes.size < 2 or bool(np.all(codes[1:] >= codes[:-1]))):
            selected = np.arange(total, dtype=np.int64)
            bounds = np.searchsorted(codes, np.arange(len(names) + 1, dtype=codes.dtype))
            used = np.flatnonzero(np.diff(bounds))
            order = used[np.argsort(np.asarray([names[c] for c in used.tolist()], dtype=object), kind="stable")]
            self._rows = [selected[bounds[c] : bounds[c + 1]] for c in order.tolist()]
            self._shard_rows: npt.NDArray[np.integer[Any]] = dataset.samples.rows
        else:
            keep = np.zeros(total, dtype=bool)
            keep[dataset.chosen_rows(rows, objects)] = True
            selected = np.flatnonzero(keep)
            used = np.unique(codes[selected])
            order = used[np.argsort(np.asarray([names[c] for c in used.tolist()], dtype=object), kind="stable")]
            position = np.full(len(names), -1, dtype=np.int64)
            position[order] = np.arange(order.size, dtype=np.int64)
            owner = position[codes[selected]]
            grouped = np.argsort(owner, kind="stable")
            cuts = np.searchsorted(owner[grouped], np.arange(order.size + 1))
            self._rows = [selected[grouped[a:b]] for a, b in itertools.pairwise(cuts.tolist())]
            self._shard_rows = np.full(total, -1, dtype=np.int32)
            self._shard_rows[selected] = dataset.samples.rows[selected]
        """Per shard: the selected dataset rows, ascending; per dataset row: its row in its shard (-1 when
        not selected)."""
        self.shards: list[str] = [names[c] for c in order.tolist()]
        """The shards holding selected rows, sorted by path."""
        self._spans = {name: span for name in self.shards if (span := dataset.samples.span(name)) is not None}
        """Where a packed dataset's shards lie (none otherwise)."""
        self.num_samples = int(selected.size)

    # -- epochs and positions -----------------------------------------------------------------
    def set_epoch(self, epoch: int) -> None:
        """Choose the epoch (call before creating the DataLoader iterator); starts at its beginning."""
        self.epoch = epoch
        self.skip = 0

    def state_dict(self, consumed: int = 0) -> dict[str, Any]:
        """The position after ``consumed`` more batches of a DataLoader iterator started at this
        stream's position: give it to `load_state_dict` to carry on from there."""
        return {
            "epoch": self.epoch,
            "skip": self.skip + consumed,
            "seed": self.seed,
            "batch_size": self.batch_size,
            "shuffle_buffer": self.shuffle_buffer,
            "drop_last": self.drop_last,
            "world_size": self.world_size,
            "num_workers": self.num_workers,
            "samples": self.num_samples,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from a `state_dict` of a stream over the same selection with the same options."""
        mine = self.state_dict()
        differ = [
            k
            for k in ("seed", "batch_size", "shuffle_buffer", "drop_last", "world_size", "samples")
            if state[k] != mine[k]
        ]
        if state.get("num_workers") is not None and self.num_workers is not None:
            differ += ["num_workers"] if state["num_workers"] != self.num_workers else []
        if differ:
            raise ValueError(f"the stream state was saved with other {', '.join(differ)}: {state}")
        if state.get("num_workers") is not None and self.num_workers is None:
            self.num_workers = int(state["num_workers"])
        self.epoch, self.skip = int(state["epoch"]), int(state["skip"])

    def loader(self, **options: Any) -> DataLoader[Batch]:
        """``DataLoader(self, batch_size=None, num_workers=self.num_workers or 0, **options)``."""
        options.setdefault("num_workers", self.num_workers or 0)
        return DataLoader(self, batch_size=None, **options)

    def __len__(self) -> int:
        """Batches this rank's DataLoader yields from the stream's position (``skip``) to the end of
        the epoch (needs ``num_workers``)."""
        if self.num_workers is None:
            raise TypeError("len(ShardStream) needs num_workers (the DataLoader's) at construction")
        workers = max(self.num_workers, 1)
        counts = self.batch_counts(workers)
        return sum(counts[self.rank * workers : (self.rank + 1) * workers]) - self.skip

    # -- the plan of an epoch (index only) ----------------------------------------------------
    def assignment(self, epoch: int, parts: int) -> list[list[int]]:
        """Per part, the shards (indices into `shards`) it reads, in order."""
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, epoch, STREAM_TAG, 1]))
        loads = np.zeros(parts, dtype=np.int64)
        assigned: list[list[int]] = [[] for _ in range(parts)]
        for shard in rng.permutation(len(self.shards)).tolist():
            part = int(np.argmin(loads))
            assigned[part].append(shard)
            loads[part] += self._rows[shard].size
        return assigned

    def batch_counts(self, workers: int, epoch: int | None = None) -> list[int]:
        """Batches each part yields in the epoch (``world_size * workers`` parts, rank-major)."""
        assigned = self.assignment(self.epoch if epoch is None else epoch, self.world_size * workers)
        sizes = [sum(self._rows[s].size for s in shards) for shards in assigned]
        if self.drop_last:
            common = min(size // self.batch_size for size in sizes)
            return [common] * len(sizes)
        return [-(-size // self.batch_size) for size in sizes]

    def part_order(self, epoch: int, workers: int, part: int) -> _Part:
        """The shards a part reads and the order its rows leave the shuffle buffer."""
        shards = self.assignment(epoch, self.world_size * workers)[part]
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, epoch, STREAM_TAG, 2, part + 1]))
        incoming = [rng.permutation(self._rows[s]) for s in shards]
        stream = np.concatenate(incoming) if incoming else np.zeros(0, dtype=np.int64)
        size = min(self.shuffle_buffer, stream.size)
        buffer = stream[:size].tolist()
        slots = rng.integers(0, max(size, 1), size=max(stream.size - size, 0)).tolist()
        order: list[int] = []
        for row, slot in zip(stream[size:].tolist(), slots, strict=True):
            order.append(buffer[slot])
            buffer[slot] = row
        order.extend(np.asarray(buffer, dtype=np.int64)[rng.permutation(len(buffer))].tolist())
        kept = self.batch_counts(workers, epoch)[part] * self.batch_size
        return _Part(shards, np.asarray(order[:kept], dtype=np.int64))

    # -- iteration ----------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Batch]:
        info = get_worker_info()
        workers, worker = (info.num_workers, info.id) if info is not None else (1, 0)
        if info is not None:
            zarr.config.set(WORKER_ZARR_CONFIG)  # a worker process is the stream's own
        expected = max(self.num_workers, 1) if self.num_workers is not None else workers
        if expected != workers:
            raise ValueError(
                f"this stream was made for {self.num_workers} DataLoader workers but runs under {workers}; "
                "give the DataLoader's num_workers to the stream (its order and skip depend on it)"
            )
        counts = self.batch_counts(workers)
        taken, turn = _round_robin(counts[self.rank * workers : (self.rank + 1) * workers], self.skip)
        # A new DataLoader starts its turns at worker 0: the worker whose turn came next plays worker 0.
        local = (turn + worker) % workers
        plan = self.part_order(self.epoch, workers, self.rank * workers + local)
        return self._batches(plan, taken[local])

    def _batches(self, plan: _Part, done: int) -> Iterator[Batch]:
        wanted = plan.order[done * self.batch_size :]
        if wanted.size == 0:
            return
        needed = np.zeros(self._shard_rows.size, dtype=bool)
        needed[wanted] = True
        shards = [s for s in plan.shards if needed[self._rows[s]].any()]
        pending: dict[int, _Prepared] = {}
        reads = _ReadAhead(self, shards, needed, self.epoch)
        try:
            for start in range(0, wanted.size, self.batch_size):
                rows = wanted[start : start + self.batch_size]
                for row in rows.tolist():
                    while row not in pending:
                        pending.update(reads.next())
                yield self._batch(rows, [pending.pop(row) for row in rows.tolist()])
        finally:
            reads.close()

    def _reader_location(self) -> Location:
        """The dataset's location, reopened once in each process (a forked worker must not use its
        parent's S3 client)."""
        if self._location is None or self._pid != os.getpid():
            self._location = open_location(self.url, self.storage_options)
            self._pid = os.getpid()
        return self._location

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_location"] = None  # reopened in the worker
        return state

    def read_shard(self, shard: int, needed: npt.NDArray[np.bool_], epoch: int) -> dict[int, _Prepared]:
        """Read shard ``shard`` whole (verified first) and hold every field of its rows that ``needed``
        marks, their clouds drawn for ``epoch`` (`storage.samples.assemble`)."""
        relative = self.shards[shard]
        reader = ShardReader(self._reader_location(), relative, verify=True, span=self._spans.get(relative))
        arrays: dict[str, npt.NDArray[Any]] = {}

        def array(name: str) -> npt.NDArray[Any]:
            """Each array decoded once per shard, whoever asks (any field)."""
            if name not in arrays:
                arrays[name] = whole_array(reader, name)
            return arrays[name]

        rows = self._rows[shard][needed[self._rows[shard]]]
        read = ShardRows(
            source=self.source,
            local=self._shard_rows[rows].astype(np.int64),
            array=array,
            rows=rows,
            schema_version=self.schema_version,
            num_views=self.num_views,
            column=lambda name: self._columns[name][rows],
            taker=lambda name: RowTaker(reader, name).take,
            draw=Draw(self.num_points, self.seed, epoch),
        )
        held = hold_samples(self.sample_fields, read)
        return {row: (held, slot) for slot, row in enumerate(rows.tolist())}

    def _batch(self, rows: npt.NDArray[np.int64], prepared: list[_Prepared]) -> Batch:
        """The batch of ``prepared`` (dataset rows ``rows``), every tensor a view of one storage (see
        `_one_storage`)."""
        by_shard: dict[int, tuple[HeldSamples, list[int], list[int]]] = {}
        for position, (held, slot) in enumerate(prepared):
            entry = by_shard.setdefault(id(held), (held, [], []))
            entry[1].append(position)
            entry[2].append(slot)
        pieces = [
            (np.asarray(positions, dtype=np.int64), take_samples(held, np.asarray(slots, dtype=np.int64)))
            for held, positions, slots in by_shard.values()
        ]
        facts = BatchFacts(
            num_views=self.num_views,
            voxel_size=self.voxel_size,
            grid_offset=self.grid_offset,
            schema_version=self.schema_version,
            source=self.source,
            rows=rows.astype(np.int64, copy=True),
        )
        batch = place_samples(pieces, len(prepared))
        values = finish_arrays(self.sample_fields, batch, np.arange(len(prepared), dtype=np.int64), facts)
        layout = {name: (found.shape, found.dtype) for name, found in values.items()}
        tensors, arrays = _one_storage(layout, shared=get_worker_info() is not None)
        for name, found in values.items():
            arrays[name][...] = found
        return SampleBatch.of(tensors)


def _one_storage(
    layout: dict[str, tuple[tuple[int, ...], np.dtype[Any]]], shared: bool
) -> tuple[dict[str, torch.Tensor], dict[str, npt.NDArray[Any]]]:
    """Tensors of the given shapes and dtypes, by name, all views of one new storage (each at a
    64-byte boundary, contiguous), and numpy views of the same memory to fill them through.

    Why one storage: a DataLoader worker sends each tensor's storage to the main process by its own
    shared-memory segment (created, mapped, its descriptor passed and received), which for a batch of
    a dozen tensors cost more CPU than building it; one storage is one segment. ``shared`` (in a
    worker) creates it in shared memory at once, as the DataLoader's own collate does, so sending it
    copies nothing. What this costs a consumer: a tensor kept alone keeps its whole batch's memory.
    """
    places: dict[str, tuple[int, int]] = {}
    total = 0
    for name, (shape, dtype) in layout.items():
        size = math.prod(shape) * dtype.itemsize
        places[name] = (total, size)
        total += -(-size // 64) * 64
    storage = _shared_storage(total) if shared else None
    storage = torch.UntypedStorage(total) if storage is None else storage
    block = torch.empty(0, dtype=torch.uint8).set_(storage)
    tensors: dict[str, torch.Tensor] = {}
    arrays: dict[str, npt.NDArray[Any]] = {}
    for name, (shape, dtype) in layout.items():
        start, size = places[name]
        tensor = block[start : start + size].view(_torch_dtype(dtype)).view(shape)
        tensors[name], arrays[name] = tensor, tensor.numpy()
    return tensors, arrays


def _shared_storage(size: int) -> torch.UntypedStorage | None:
    """A storage of ``size`` bytes in shared memory, as the DataLoader's own collate makes one (a
    private torch method); None where this torch lacks it (the DataLoader then moves the storage to
    shared memory itself: a copy, not a failure)."""
    make = getattr(torch.UntypedStorage, "_new_shared", None)
    return make(size) if make is not None else None


def _torch_dtype(dtype: np.dtype[Any]) -> torch.dtype:
    """torch's dtype for a numpy one (the one `torch.from_numpy` gives, so `SampleBatch.tensors`'s)."""
    return torch.from_numpy(np.empty(0, dtype=dtype)).dtype


class _ReadAhead:
    """Shards read in order by background threads, up to ``read_ahead`` ahead of the consumer; a
    failure (a damaged shard) is raised by `next` where the consumer meets that shard."""

    def __init__(self, stream: ShardStream, shards: list[int], needed: npt.NDArray[np.bool_], epoch: int) -> None:
        self._stream, self._needed, self._epoch = stream, needed, epoch
        self._todo = iter(shards)
        self._pool = ThreadPoolExecutor(max_workers=stream.read_ahead, thread_name_prefix="shard-stream")
        self._flight: queue.SimpleQueue[Future[dict[int, _Prepared]]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        for _ in range(stream.read_ahead + 1):
            self._submit()

    def _submit(self) -> None:
        with self._lock:
            shard = next(self._todo, None)
            if shard is not None:
                self._flight.put(self._pool.submit(self._stream.read_shard, shard, self._needed, self._epoch))

    def next(self) -> dict[int, _Prepared]:
        try:
            future = self._flight.get_nowait()
        except queue.Empty:
            raise RuntimeError("the stream ran out of shards before its order did (a bug)") from None
        found = future.result()
        self._submit()
        return found

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def _round_robin(counts: Sequence[int], taken: int) -> tuple[list[int], int]:
    """How many of the first ``taken`` batches of a DataLoader came from each worker, when worker w
    yields ``counts[w]`` batches and the DataLoader takes them in turn, skipping exhausted workers;
    and whose turn comes next."""
    left, mine, turn = list(counts), [0] * len(counts), 0
    if taken > sum(left):
        raise ValueError(f"skip = {taken} batches, but the epoch holds only {sum(left)} for this rank")
    while taken > 0:
        if left[turn]:
            left[turn] -= 1
            mine[turn] += 1
            taken -= 1
        turn = (turn + 1) % len(left)
    return mine, turn


def _distributed(rank: int | None, world_size: int | None) -> tuple[int, int]:
    """(rank, world size): the ones given, else torch.distributed's when initialised, else (0, 1)."""
    initialised = torch.distributed.is_available() and torch.distributed.is_initialized()
    if world_size is None:
        world_size = torch.distributed.get_world_size() if initialised else 1
    if rank is None:
        rank = torch.distributed.get_rank() if initialised else 0
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} of world size {world_size}: need 0 <= rank < world_size")
    return rank, world_size
