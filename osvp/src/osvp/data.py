"""Samples in memory for training: read once through `storage`, then batched without a reader.

A CPU epoch over a few thousand samples must not wait on Zarr reads, so `SampleBank.load` reads
every sample's integer keys once through `storage.readers.memory` (shard by shard, the reader's fast order),
packed in one int16 array with offsets; a batch is then a numpy gather. Each sample is resampled to
a fixed point count from its own stream (seed, epoch, sample), so batches never depend on batch
size, order or device, and a resumed run sees exactly the tensors an uninterrupted one would; the
conversions and the splits are the sample contract's (`storage.samples`: its resampling and splits),
every reader's.
A version-2 dataset also gives every sample's minimum covers (`osvp.covers.CoverBank`), which the
ambiguity-aware targets and metrics need; a version-1 dataset has none (`require_covers` says how
to add them).

Learning curves train on nested, seeded subsets of the training side (`training_subset`): the
validation rows never depend on them, so every point of a curve is judged on the same samples.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch

import storage
from osvp.covers import CoverBank
from schemas.errors import DatagenError
from storage.readers import MemoryDataset, load_memory
from storage.samples import SampleBatch, SplitError, split_by_object, split_by_sample

Split = Literal["samples", "objects"]

SUBSET_STREAM = 0x5B5E7
"""Tag of the training-subset streams (seed, tag, 1: objects; seed, tag, 2: samples), apart from
the split's (seed, count) and the epochs' (seed, epoch, k) streams."""


class DataError(DatagenError):
    """A dataset cannot be used for training as asked (empty, too few samples or objects to split)."""


Batch = SampleBatch[torch.Tensor]
"""A training batch: the sample contract's one batch type (`storage.samples.SampleBatch`), as tensors."""


@dataclass(frozen=True)
class SampleBank:
    """Every sample of a dataset in memory (`storage.readers.MemoryDataset`: keys packed with
    offsets, view states and labels as bit rows), with its minimum covers as a `CoverBank`."""

    samples: MemoryDataset
    covers: CoverBank | None = None
    """Every sample's minimum covers; None for a version-1 dataset."""

    @property
    def url(self) -> str:
        return self.samples.url

    @property
    def config_hash(self) -> str:
        """The dataset's own record (``dataset.json``): recomputing it would hash this machine's datagen files."""
        return self.samples.config_hash

    @property
    def keys(self) -> npt.NDArray[np.int16]:
        return self.samples.keys

    @property
    def offsets(self) -> npt.NDArray[np.int64]:
        return self.samples.offsets

    @property
    def view_state(self) -> npt.NDArray[np.float32]:
        return self.samples.view_state

    @property
    def labels(self) -> npt.NDArray[np.float32]:
        return self.samples.labels

    @property
    def object_ids(self) -> tuple[str, ...]:
        """Object of each sample."""
        return self.samples.object_ids

    @property
    def voxel_size(self) -> float:
        return self.samples.voxel_size

    @property
    def grid_offset(self) -> npt.NDArray[np.float64]:
        return self.samples.grid_offset

    @property
    def schema_version(self) -> int:
        return self.samples.schema_version

    @property
    def num_views(self) -> int:
        return self.samples.num_views

    def __len__(self) -> int:
        return len(self.samples)

    @classmethod
    def load(
        cls,
        url: str,
        source: Literal["points", "observed"] = "points",
        progress: Callable[[int, int], None] | None = None,
        covers_for: str | None = None,
        fields: Sequence[str] = (),
    ) -> SampleBank:
        """Read every sample of the dataset at ``url`` (`storage.StorageError` names damage and the fix).
        ``covers_for`` names what needs the minimum covers: a dataset without them is refused before
        any sample is read; ``fields`` names optional sample fields to hold too (``grid``)."""
        dataset = storage.open_dataset(url)
        if covers_for is not None and not dataset.has_ambiguity:
            raise no_covers(url, dataset.info.schema_version, covers_for)
        if len(dataset) == 0:
            raise DataError(f"{url}: holds no samples; generate a dataset with `datagen submit` first")
        return cls.from_memory(load_memory(dataset, source, progress=progress, fields=fields))

    @classmethod
    def from_memory(cls, samples: MemoryDataset) -> SampleBank:
        """A bank over samples `storage.readers.load_memory` read (its covers become a `CoverBank`)."""
        packed = samples.covers
        covers = None
        if packed is not None:
            held = samples.fields.get("marginals")  # read with the covers by the load: not computed twice
            covers = CoverBank.from_packed(packed, samples.view_state_masks, samples.num_views, held)
        return cls(samples=samples, covers=covers)

    def batch(
        self,
        rows: Sequence[int] | npt.NDArray[np.int64],
        num_points: int,
        seed: int,
        epoch: int,
        with_covers: bool = False,
    ) -> Batch:
        """Samples ``rows``, each resampled to ``num_points`` from stream (seed, epoch, row); with
        marginals and support when the dataset has covers, and the padded covers if asked for (one
        path for every field: `storage.samples.assemble`)."""
        return self.samples.batch(rows, num_points, seed, epoch, covers=with_covers).tensors()


def require_covers(bank: SampleBank, what: str) -> CoverBank:
    """The bank's covers, or one `DataError` line naming the relabel that adds them."""
    if bank.covers is None:
        raise no_covers(bank.url, bank.schema_version, what)
    return bank.covers


def no_covers(url: str, schema_version: int, what: str) -> DataError:
    """``what`` cannot work on the dataset at ``url``: it keeps no minimum covers."""
    return DataError(
        f"{url}: {what} needs every sample's minimum covers, which a version-{schema_version} dataset does not "
        f"keep; add them with `datagen shards relabel {url} --out NEW_URL` and use NEW_URL"
    )


def split_rows(
    bank: SampleBank, how: Split = "samples", val_fraction: float = 0.2, seed: int = 0
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(train, validation) sample rows: a seeded 80/20 split of the samples (the paper's) or of the
    objects (``objects``: no object on both sides, a test of generalisation to unseen shapes)."""
    if not 0.0 < val_fraction < 1.0:
        raise DataError(f"validation fraction {val_fraction} must lie strictly between 0 and 1")
    if how == "samples":
        try:
            return split_by_sample(len(bank), val_fraction, seed)
        except SplitError as exc:
            raise DataError(f"{bank.url}: {exc}") from None
    if how != "objects":
        raise DataError(f"unknown split {how!r}; use 'samples' or 'objects'")
    if len(set(bank.object_ids)) < 2:
        raise DataError(f"{bank.url}: one object cannot be split by object; use --split samples")
    return split_by_object(bank.object_ids, val_fraction, seed)


def training_subset(
    bank: SampleBank,
    train_rows: npt.NDArray[np.int64],
    max_objects: int | None = None,
    sample_fraction: float = 1.0,
    seed: int = 0,
) -> npt.NDArray[np.int64]:
    """The training rows a learning-curve point trains on: the samples of ``max_objects`` of the
    training side's objects, then a ``sample_fraction`` of those samples (at least one).

    Both draws are nested for a seed: the objects are a prefix of one seeded permutation of the
    training objects (the first 10 of a 20 draw are the 10 draw), and the samples are those with
    the smallest keys of one seeded key per dataset row (a 0.25 draw lies inside the 0.5 draw).
    """
    rows = np.asarray(train_rows, dtype=np.int64)
    if max_objects is not None:
        objects = sorted({bank.object_ids[i] for i in rows.tolist()})
        if not 1 <= max_objects <= len(objects):
            raise DataError(
                f"max objects {max_objects}: the training side holds {len(objects)} objects; give 1 to {len(objects)}"
            )
        order = np.random.default_rng(np.random.SeedSequence([seed, SUBSET_STREAM, 1])).permutation(len(objects))
        kept = {objects[i] for i in order[:max_objects].tolist()}
        rows = rows[np.array([bank.object_ids[i] in kept for i in rows.tolist()], dtype=bool)]
    check_sample_fraction(sample_fraction)
    if sample_fraction < 1.0:
        keys = np.random.default_rng(np.random.SeedSequence([seed, SUBSET_STREAM, 2])).random(len(bank))
        count = max(1, int(np.floor(sample_fraction * rows.size + 0.5)))
        rows = np.sort(rows[np.argsort(keys[rows], kind="stable")[:count]])
    return rows


def check_sample_fraction(fraction: float) -> None:
    """Refuse a fraction outside (0, 1] (`TrainOptions.check` calls it before any sample is read)."""
    if not 0.0 < fraction <= 1.0:
        raise DataError(f"sample fraction {fraction} must lie in (0, 1]")
