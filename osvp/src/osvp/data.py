"""Samples in memory for training: read once through `storage`, then batched without a reader.

A CPU epoch over a few thousand samples must not wait on Zarr reads, so `SampleBank.load` reads
every sample's integer keys once (shard by shard, the reader's fast order) and keeps them packed
in one int16 array with offsets; a batch is then a numpy gather. Each sample is resampled to a
fixed point count from its own stream (seed, epoch, sample), so batches never depend on batch
size, order or device, and a resumed run sees exactly the tensors an uninterrupted one would.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch

import storage
from schemas.errors import DatagenError

Split = Literal["samples", "objects"]


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
    ) -> SampleBank:
        """Read every sample of the dataset at ``url`` (`storage.StorageError` names damage and the fix)."""
        dataset = storage.open_dataset(url)
        total = len(dataset)
        if total == 0:
            raise DataError(f"{url}: holds no samples; generate a dataset with `datagen submit` first")
        width = dataset.num_views
        counts = np.zeros(total, dtype=np.int64)
        pieces: list[npt.NDArray[np.int16] | None] = [None] * total
        state = np.zeros((total, width), dtype=np.float32)
        labels = np.zeros((total, width), dtype=np.float32)
        bits = np.arange(width, dtype=np.uint64)
        done = 0
        for block in dataset.shard_blocks():
            for i in block.tolist():
                keys = dataset.keys(i, source)
                pieces[i], counts[i] = keys, keys.shape[0]
                view_state, label = dataset.masks(i)
                state[i] = (np.uint64(view_state) >> bits) & np.uint64(1)
                labels[i] = (np.uint64(label) >> bits) & np.uint64(1)
            done += block.size
            if progress:
                progress(done, total)
        offsets = np.zeros(total + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        packed = np.concatenate([p for p in pieces if p is not None]) if offsets[-1] else np.zeros((0, 3), np.int16)
        config = dataset.info.config
        return cls(
            url=url,
            config_hash=config.config_hash(),
            keys=packed.astype(np.int16, copy=False),
            offsets=offsets,
            view_state=state,
            labels=labels,
            object_ids=tuple(dataset.index.column("object_id").to_pylist()),
            voxel_size=float(config.voxel_size),
            grid_offset=np.asarray(config.grid_offset, dtype=np.float64),
        )

    def batch(self, rows: Sequence[int] | npt.NDArray[np.int64], num_points: int, seed: int, epoch: int) -> Batch:
        """Samples ``rows``, each resampled to ``num_points`` from stream (seed, epoch, row)."""
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
        return Batch(
            points=torch.from_numpy(centres),
            view_state=torch.from_numpy(self.view_state[index]),
            labels=torch.from_numpy(self.labels[index]),
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
