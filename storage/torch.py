"""PyTorch access: `OSVPDataset` (fixed-size point clouds, view state, label) and a shard-aware
sampler. Importing `storage` never imports torch; importing this module does.

Resampling to ``num_points`` depends only on (seed, epoch, index), never on worker count or order,
so two runs with the same seeds see identical tensors (`storage.resampling` and `storage.batch`, the
contract every reader shares: `storage.memory` and osvp give the same tensors for the same seed, epoch and index). Shard
handles are opened lazily in each worker process (fork and spawn both work: the dataset pickles
without them). A damaged dataset is a
`storage.StorageError` naming the file and the fix, never a silently zeroed sample (`storage.reader`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal

import torch
from torch.utils.data import DataLoader, Sampler
from torch.utils.data import Dataset as TorchDataset

from storage.batch import SampleBatch, Source, check_source
from storage.bits import bit_rows
from storage.reader import Dataset, open_dataset

Item = dict[str, torch.Tensor]
"""One sample: the fields of a `SampleBatch` without the batch axis (what a DataLoader's default
collation stacks into a dict of the same names)."""


def collate_samples(items: Sequence[Mapping[str, torch.Tensor]]) -> SampleBatch[torch.Tensor]:
    """The `SampleBatch` of ``items`` (each field stacked): `OSVPDataset.loader`'s collation."""
    if not items:
        raise ValueError("no samples to collate")
    return SampleBatch(**{name: torch.stack([item[name] for item in items]) for name in items[0]})


class OSVPDataset(TorchDataset[Item]):
    """Samples as tensors: ``points`` (num_points, 3) float32, ``view_state`` and ``label`` (n,)
    float32 (0/1), plus ``index``; `loader` batches them as `storage.batch.SampleBatch`."""

    def __init__(
        self,
        url: str,
        num_points: int = 2048,
        source: Source = "points",
        split: Literal["train", "val"] | None = None,
        val_fraction: float = 0.2,
        seed: int = 0,
        split_seed: int = 0,
        storage_options: dict[str, Any] | None = None,
    ) -> None:
        check_source(source)
        if num_points < 1:
            raise ValueError(f"num_points = {num_points} must be >= 1")
        dataset = open_dataset(url, storage_options)
        if split is not None:
            train, val = dataset.split(val_fraction, split_seed)
            dataset = train if split == "train" else val
        self.dataset: Dataset = dataset
        self.num_points = num_points
        self.source = source
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Choose the resampling of this epoch (call before creating the DataLoader iterator)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> Item:
        index = range(len(self))[index]  # negative indices as for any sequence
        keys = self.dataset.resampled_keys(index, self.num_points, self.seed, self.epoch, self.source)
        view_state, label = self.dataset.masks(index)
        width = self.dataset.num_views
        return {
            "points": torch.from_numpy(self.dataset.centres(keys)),
            "view_state": torch.from_numpy(bit_rows(view_state, width)),
            "label": torch.from_numpy(bit_rows(label, width)),
            "index": torch.tensor(index),
        }

    def loader(self, batch_size: int = 32, shuffle_seed: int | None = None, **options: Any) -> DataLoader[Item]:
        """A DataLoader of `SampleBatch` batches: in index order, or with ``shuffle_seed`` in a
        `ShardShuffleSampler`'s order (call its ``set_epoch`` with this dataset's); ``options`` go to
        the DataLoader."""
        sampler = ShardShuffleSampler(self, shuffle_seed) if shuffle_seed is not None else None
        return DataLoader(self, batch_size=batch_size, sampler=sampler, collate_fn=collate_samples, **options)


class ShardShuffleSampler(Sampler[int]):
    """Shuffled order that visits shards a few at a time, mixing their samples (see
    `Dataset.shuffled_order`): random enough for training, and each worker keeps hitting the few
    shards it has cached, which is what makes the DataLoader fast."""

    def __init__(self, dataset: OSVPDataset, seed: int = 0, shards_mixed: int = 4) -> None:
        self.dataset = dataset
        self.seed = seed
        self.shards_mixed = shards_mixed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.dataset)

    def __iter__(self) -> Iterator[int]:
        order = self.dataset.dataset.shuffled_order(self.seed, self.epoch, self.shards_mixed)
        return iter(order.tolist())
