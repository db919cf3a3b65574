"""The loader classes MA-SCVP's PC-NBV ``train.py`` imports from ``dataset.dataset``, absent from their release.

``ShapeNet3(clouds, ground_truths, view_states, targets)`` is all their ``train.py`` uses: four paths of
tensors saved by ``torch.save``, sample i being row i of each (what ``datagen shards export --layout
pcnbv`` writes, and what the argument names and train.py's use of the batches imply: clouds (B, P, 3)
permuted to (B, 3, P), view states (B, 32), targets (B, 32) compared with the network's 32 outputs).
``ShapeNet`` (upstream PC-NBV's loader of per-case ``.npy`` files and ``.mat`` ground truths) and
``ShapeNet2`` (a folder reader of the authors', never released) are not used by train.py: they are
named so its import succeeds, and refuse to be built.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.utils.data import Dataset


class ShapeNet3(Dataset):  # type: ignore[type-arg]
    """Row i of four saved tensors: (accumulated cloud, ground-truth cloud, view state, target values)."""

    def __init__(self, clouds: str, ground_truths: str, view_states: str, targets: str) -> None:
        self.tensors = [torch.load(path) for path in (clouds, ground_truths, view_states, targets)]
        counts = {len(tensor) for tensor in self.tensors}
        if len(counts) != 1:
            raise ValueError(f"the four tensors hold different sample counts: {sorted(counts)}")

    def __len__(self) -> int:
        return len(self.tensors[0])

    def __getitem__(self, index: int) -> tuple[Any, ...]:
        return tuple(tensor[index] for tensor in self.tensors)


class _Unreleased(Dataset):  # type: ignore[type-arg]
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        raise NotImplementedError(f"{type(self).__name__} is not released by the authors; train.py uses ShapeNet3")


class ShapeNet(_Unreleased):
    pass


class ShapeNet2(_Unreleased):
    pass
