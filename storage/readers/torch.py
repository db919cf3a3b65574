"""PyTorch access: `OSVPDataset` (fixed-size point clouds, view state, label) and a shard-aware
sampler. Importing `storage` never imports torch; importing this module does.

Resampling to ``num_points`` depends only on (seed, epoch, index), never on worker count or order,
so two runs with the same seeds see identical tensors (`storage.samples.resampling` and
`storage.samples.batch`, the contract every reader shares: `storage.readers.memory` and osvp give the
same tensors for the same seed, epoch and index). Shard
handles are opened lazily in each worker process (fork and spawn both work: the dataset pickles
without them). A damaged dataset is a
`storage.StorageError` naming the file and the fix, never a silently zeroed sample (`storage.readers.reader`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal

import numpy as np
import torch
from torch.utils.data import DataLoader, Sampler
from torch.utils.data import Dataset as TorchDataset

from storage.readers.reader import Dataset, open_dataset
from storage.samples.assemble import finish_arrays, hold_samples
from storage.samples.batch import SampleBatch, Source, check_source
from storage.samples.sample_fields import SAMPLE_FIELDS, Draw, fields_for

Item = dict[str, torch.Tensor]
"""One sample: the fields of a `SampleBatch` without the batch axis (what a DataLoader's default
collation stacks into a dict of the same names)."""


def collate_samples(items: Sequence[Mapping[str, torch.Tensor]]) -> SampleBatch[torch.Tensor]:
    """The `SampleBatch` of ``items`` (each field stacked): `OSVPDataset.loader`'s collation."""
    if not items:
        raise ValueError("no samples to collate")
    return SampleBatch.of({name: torch.stack([item[name] for item in items]) for name in items[0]})


class OSVPDataset(TorchDataset[Item]):
    """Samples as tensors: ``points`` (num_points, 3) float32, ``view_state`` and ``label`` (n,)
    float32 (0/1), ``index``, and every other registered field the dataset has (``fields`` names
    optional ones, e.g. ``grid``), each read and made by `storage.samples.assemble` as the other readers make
    it; `loader` batches them as `storage.samples.SampleBatch`. The listed covers (a listing a sample,
    padded per batch) are `storage.stream.ShardStream`'s and `storage.readers.memory`'s."""

    def __init__(
        self,
        url: str,
        num_points: int = 2048,
        source: Source = "points",
        split: Literal["train", "val"] | None = None,
        val_fraction: float = 0.2,
        seed: int = 0,
        split_seed: int = 0,
        fields: Sequence[str] = (),
        storage_options: dict[str, Any] | None = None,
    ) -> None:
        check_source(source)
        if num_points < 1:
            raise ValueError(f"num_points = {num_points} must be >= 1")
        padded = [name for name in fields if name in SAMPLE_FIELDS and SAMPLE_FIELDS[name].padded]
        if padded:
            raise ValueError(
                f"fields: {', '.join(padded)} vary in length per sample; read them with "
                "storage.stream.ShardStream(covers=True) or storage.readers.load_memory(...).batch(covers=True)"
            )
        dataset = open_dataset(url, storage_options)
        if split is not None:
            train, val = dataset.split(val_fraction, split_seed)
            dataset = train if split == "train" else val
        self.dataset: Dataset = dataset
        self.sample_fields = fields_for(dataset.info.schema_version, fields, has_covers=dataset.has_ambiguity)
        """The registered `storage.samples.SampleField`s an item has."""
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
        found = self.dataset
        read = found.shard_rows(index, self.source, Draw(self.num_points, self.seed, self.epoch), whole_columns=True)
        held = hold_samples(self.sample_fields, read)
        arrays = finish_arrays(self.sample_fields, held, np.zeros(1, dtype=np.int64), found.batch_facts(read))
        return {name: torch.from_numpy(np.asarray(values[0])) for name, values in arrays.items()}

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
