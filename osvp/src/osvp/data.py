"""Samples in memory for training: read once through `storage`, then batched without a reader.

A CPU epoch over a few thousand samples must not wait on Zarr reads, so `SampleBank.load` reads
every sample's integer keys once (shard by shard, the reader's fast order) and keeps them packed
in one int16 array with offsets; a batch is then a numpy gather. Each sample is resampled to a
fixed point count from its own stream (seed, epoch, sample), so batches never depend on batch
size, order or device, and a resumed run sees exactly the tensors an uninterrupted one would.
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

Split = Literal["samples", "objects"]

SUBSET_STREAM = 0x5B5E7
"""Tag of the training-subset streams (seed, tag, 1: objects; seed, tag, 2: samples), apart from
the split's (seed, count) and the epochs' (seed, epoch, k) streams."""


class DataError(DatagenError):
    """A dataset cannot be used for training as asked (empty, too few samples or objects to split)."""


@dataclass(frozen=True)
class Batch:
    points: torch.Tensor
    """(B, N, 3) float32 key centres, metres."""
    view_state: torch.Tensor
    """(B, n) float32 0/1."""
    labels: torch.Tensor
    """(B, n) float32 0/1."""
    marginals: torch.Tensor | None = None
    """(B, n) float32: fraction of the listed minimum covers holding each view (version 2)."""
    support: torch.Tensor | None = None
    """(B, n) float32 0/1: views in any minimum cover (version 2)."""
    covers: torch.Tensor | None = None
    """(B, C, n) float32 0/1: the listed minimum covers, padded (only when asked for)."""
    cover_mask: torch.Tensor | None = None
    """(B, C) bool: True where ``covers`` holds a real cover."""


@dataclass(frozen=True)
class SampleBank:
    """Every sample of a dataset: keys packed with offsets, view states and labels as bit rows."""

    url: str
    config_hash: str
    keys: npt.NDArray[np.int16]
    offsets: npt.NDArray[np.int64]
    view_state: npt.NDArray[np.float32]
    labels: npt.NDArray[np.float32]
    object_ids: tuple[str, ...]
    """Object of each sample."""
    voxel_size: float
    grid_offset: npt.NDArray[np.float64]
    schema_version: int = 1
    covers: CoverBank | None = None
    """Every sample's minimum covers; None for a version-1 dataset."""

    @property
    def num_views(self) -> int:
        return int(self.labels.shape[1])

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @classmethod
    def load(
        cls,
        url: str,
        source: Literal["points", "observed"] = "points",
        progress: Callable[[int, int], None] | None = None,
        covers_for: str | None = None,
    ) -> SampleBank:
        """Read every sample of the dataset at ``url`` (`storage.StorageError` names damage and the fix).
        ``covers_for`` names what needs the minimum covers: a dataset without them is refused before
        any sample is read."""
        dataset = storage.open_dataset(url)
        if covers_for is not None and not dataset.has_ambiguity:
            raise no_covers(url, dataset.info.schema_version, covers_for)
        total = len(dataset)
        if total == 0:
            raise DataError(f"{url}: holds no samples; generate a dataset with `datagen submit` first")
        width = dataset.num_views
        counts = np.zeros(total, dtype=np.int64)
        pieces: list[npt.NDArray[np.int16] | None] = [None] * total
        state = np.zeros((total, width), dtype=np.float32)
        labels = np.zeros((total, width), dtype=np.float32)
        bits = np.arange(width, dtype=np.uint64)
        ambiguous = dataset.has_ambiguity
        ambiguities: list[storage.LabelAmbiguity | None] = [None] * total
        state_masks = np.zeros(total, dtype=np.uint64)
        done = 0
        for block in dataset.shard_blocks():
            for i in block.tolist():
                keys = dataset.keys(i, source)
                pieces[i], counts[i] = keys, keys.shape[0]
                view_state, label = dataset.masks(i)
                state[i] = (np.uint64(view_state) >> bits) & np.uint64(1)
                labels[i] = (np.uint64(label) >> bits) & np.uint64(1)
                state_masks[i] = view_state
                if ambiguous:
                    ambiguities[i] = dataset.ambiguity(i)
            done += block.size
            if progress:
                progress(done, total)
        offsets = np.zeros(total + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        packed = np.concatenate([p for p in pieces if p is not None]) if offsets[-1] else np.zeros((0, 3), np.int16)
        config = dataset.info.config
        found = [a for a in ambiguities if a is not None]
        return cls(
            url=url,
            # The dataset's own record: recomputing it would hash this machine's datagen files.
            config_hash=dataset.info.config_hash,
            keys=packed.astype(np.int16, copy=False),
            offsets=offsets,
            view_state=state,
            labels=labels,
            object_ids=tuple(dataset.index.column("object_id").to_pylist()),
            voxel_size=float(config.voxel_size),
            grid_offset=np.asarray(config.grid_offset, dtype=np.float64),
            schema_version=dataset.info.schema_version,
            covers=CoverBank.build(found, state_masks.tolist(), width) if ambiguous else None,
        )

    def batch(
        self,
        rows: Sequence[int] | npt.NDArray[np.int64],
        num_points: int,
        seed: int,
        epoch: int,
        with_covers: bool = False,
    ) -> Batch:
        """Samples ``rows``, each resampled to ``num_points`` from stream (seed, epoch, row); with
        marginals and support when the dataset has covers, and the padded covers if asked for."""
        chosen = np.zeros((len(rows), num_points, 3), dtype=np.int16)
        for slot, row in enumerate(np.asarray(rows, dtype=np.int64).tolist()):
            start, stop = int(self.offsets[row]), int(self.offsets[row + 1])
            count = stop - start
            if count == 0:
                continue  # an empty cloud stays at the zero key, as storage's OSVPDataset does
            rng = np.random.default_rng(np.random.SeedSequence([seed, epoch, row]))
            picks = rng.choice(count, size=num_points, replace=count < num_points, shuffle=False)
            chosen[slot] = self.keys[start + picks]
        centres = ((chosen.astype(np.float64) + 0.5 - self.grid_offset) * self.voxel_size).astype(np.float32)
        index = np.asarray(rows, dtype=np.int64)
        found = self.covers
        covers, valid = found.padded(index) if found is not None and with_covers else (None, None)
        return Batch(
            points=torch.from_numpy(centres),
            view_state=torch.from_numpy(self.view_state[index]),
            labels=torch.from_numpy(self.labels[index]),
            marginals=torch.from_numpy(found.marginals[index]) if found is not None else None,
            support=torch.from_numpy(found.support[index]) if found is not None else None,
            covers=torch.from_numpy(covers) if covers is not None else None,
            cover_mask=torch.from_numpy(valid) if valid is not None else None,
        )


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
    total = len(bank)
    if how == "samples":
        order = np.random.default_rng(np.random.SeedSequence([seed, total])).permutation(total)
        cut = max(1, round(val_fraction * total))
        if cut >= total:
            raise DataError(f"{bank.url}: {total} samples are too few to split; generate more")
        return np.sort(order[cut:]), np.sort(order[:cut])
    if how != "objects":
        raise DataError(f"unknown split {how!r}; use 'samples' or 'objects'")
    objects = sorted(set(bank.object_ids))
    if len(objects) < 2:
        raise DataError(f"{bank.url}: one object cannot be split by object; use --split samples")
    order = np.random.default_rng(np.random.SeedSequence([seed, len(objects)])).permutation(len(objects))
    held = {objects[i] for i in order[: max(1, round(val_fraction * len(objects)))]}
    in_val = np.array([o in held for o in bank.object_ids], dtype=bool)
    return np.flatnonzero(~in_val), np.flatnonzero(in_val)


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
