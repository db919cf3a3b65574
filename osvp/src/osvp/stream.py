"""Training from a stream: when a dataset does not fit in memory, each epoch reads the training
samples shard by shard (`storage.stream.ShardStream`, in DataLoader workers) instead of from a
`osvp.data.SampleBank`.

`memory_estimate` is what a `SampleBank` of the dataset would hold, from the index alone (its point
counts): 6 bytes a point, plus the per-sample rows; `choose_streaming` streams when that exceeds the
limit (``osvp train --memory-limit``, 8 GB by default) or when asked (``--stream``).

In streaming mode the validation rows stay in memory: `index_bank` is a `SampleBank` of every sample's
index facts (object, view state, label; no clouds), on which the split and the training subset are
drawn exactly as in memory; `rows_bank` then reads the clouds and covers of the validation rows only
(`storage.readers.load_memory`), at most ``val_cap`` of them (a seeded draw, `cap_rows`). Every sample
resamples from its dataset row's stream (seed, epoch, row), so a streamed batch holds the clouds
`SampleBank.batch` gives, and the validation clouds are the in-memory ones.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch

import storage
from osvp.data import Batch, DataError, SampleBank, no_covers
from storage.readers import load_index_facts, load_memory
from storage.samples import PACKED_CELLS
from storage.stream import ShardStream

GB = 1e9
MEMORY_LIMIT_GB = 8.0
VAL_CAP = 10_000
CAP_STREAM = 0x5A1CA
"""Tag of the validation cap's stream (seed, tag)."""
POINT_BYTES = 6
"""A stored point: three int16 key coordinates."""


def memory_estimate(
    dataset: storage.Dataset, source: Literal["points", "observed"] = "points", fields: Sequence[str] = ()
) -> int:
    """Bytes a `SampleBank` of the whole dataset holds: every key, its offsets, view state and label
    rows, and with covers their support, marginals and listed covers (from the index's counts; the
    listing is capped by the config's ``label_cover_cap``), and each task's ray cells when ``fields``
    asks for the grids. Loading it briefly needs up to twice the keys."""
    column = "num_points" if source == "points" else "num_observed"
    points = int(dataset.index.column(column).to_numpy().astype(np.int64).sum())
    samples, width = len(dataset), dataset.num_views
    total = points * POINT_BYTES + samples * (8 + 2 * 4 * width)
    if dataset.has_ambiguity:
        cap = int(dataset.info.config.label_cover_cap)
        listed = np.minimum(dataset.index.column("min_covers").to_numpy().astype(np.int64), cap)
        total += samples * (2 * 4 * width + 8 + 8 + 1) + int(listed.sum()) * 8
    if "grid" in fields:  # each task's per-view ray cells (`storage.samples.CaseGrids`)
        tasks = len(set(dataset.index.column("shard").to_pylist()))
        total += tasks * 2 * width * PACKED_CELLS + samples * 16
    return total


def choose_streaming(
    url: str,
    stream: bool | None,
    memory_limit_gb: float,
    source: Literal["points", "observed"] = "points",
    fields: Sequence[str] = (),
) -> tuple[bool, str]:
    """(stream?, the line that says why) for ``osvp train``: ``stream`` True or False decides; None
    streams when `memory_estimate` exceeds the limit."""
    if stream is not None:
        return stream, "streaming the training samples (--stream)" if stream else ""
    needed = memory_estimate(storage.open_dataset(url), source, fields)
    if needed > memory_limit_gb * GB:
        return True, (
            f"streaming the training samples: in memory they need about {needed / GB:.1f} GB, over --memory-limit "
            f"{memory_limit_gb:g} GB (validation stays in memory)"
        )
    return False, ""


def open_dataset(url: str, covers_for: str | None) -> storage.Dataset:
    """The dataset (index only); refused before any read when ``covers_for`` needs covers it lacks."""
    dataset = storage.open_dataset(url)
    if covers_for is not None and not dataset.has_ambiguity:
        raise no_covers(url, dataset.info.schema_version, covers_for)
    if len(dataset) == 0:
        raise DataError(f"{url}: holds no samples; generate a dataset with `datagen submit` first")
    return dataset


def index_bank(dataset: storage.Dataset, source: Literal["points", "observed"] = "points") -> SampleBank:
    """A `SampleBank` of every sample holding no cloud and no covers: the index's facts (object,
    view state, label), enough to draw the split and the training subset as in memory."""
    return SampleBank(samples=load_index_facts(dataset, source))


def cap_rows(rows: npt.NDArray[np.int64], cap: int, seed: int) -> npt.NDArray[np.int64]:
    """At most ``cap`` of ``rows`` (0: all), a seeded draw, sorted."""
    if cap <= 0 or rows.size <= cap:
        return rows
    chosen = np.random.default_rng(np.random.SeedSequence([seed, CAP_STREAM])).choice(rows, cap, replace=False)
    return np.sort(chosen)


def rows_bank(
    dataset: storage.Dataset,
    rows: npt.NDArray[np.int64],
    source: Literal["points", "observed"] = "points",
    fields: Sequence[str] = (),
) -> SampleBank:
    """The samples ``rows`` in memory, with their minimum covers (position p is dataset row
    ``rows[p]``, and resamples from that row's stream, as in a whole load)."""
    return SampleBank.from_memory(load_memory(dataset, source, rows=rows, fields=fields))


class StreamedRows:
    """The training rows as a stream of `osvp.data.Batch`, one DataLoader per epoch."""

    def __init__(
        self,
        dataset: storage.Dataset,
        rows: npt.NDArray[np.int64],
        num_points: int,
        batch_size: int,
        seed: int,
        source: Literal["points", "observed"] = "points",
        covers: bool = False,
        workers: int = 2,
        shuffle_buffer: int = 4096,
        pin_memory: bool = False,
        fields: Sequence[str] = (),
    ) -> None:
        self.stream = ShardStream(
            dataset,
            rows=rows,
            num_points=num_points,
            batch_size=batch_size,
            source=source,
            seed=seed,
            shuffle_buffer=shuffle_buffer,
            covers=covers,
            fields=fields,
            num_workers=workers,
            rank=0,
            world_size=1,
        )
        self.workers = workers
        self.pin_memory = pin_memory

    def __len__(self) -> int:
        """Samples of an epoch."""
        return self.stream.num_samples

    def epoch(self, epoch: int) -> Iterator[Batch]:
        """The batches of ``epoch``; the DataLoader draws its worker seeds from its own generator,
        never from torch's global RNG."""
        self.stream.set_epoch(epoch)
        loader = self.stream.loader(
            num_workers=self.workers,
            pin_memory=self.pin_memory,
            generator=torch.Generator().manual_seed(epoch),
        )
        yield from loader
