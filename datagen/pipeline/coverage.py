"""Filter and coverage (docs/pipeline.md section 5): P_i, count, P_full and the coverage sets C_i.

Every key of the union of the P_i gets the bit mask of the views whose P_i contain it; count is its
popcount. P_full keeps the keys with count >= alpha, and C_i is then "bit i of the mask" on P_full:
one uint64 per key holds every coverage set at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.setcover import MaskArray, popcount


@dataclass(frozen=True)
class Coverage:
    """The coverage table of one task for one alpha."""

    keys: npt.NDArray[np.int64]
    """P_full as sorted packed keys."""
    masks: MaskArray
    """For each key of P_full, the views i with the key in C_i (bit i)."""
    alpha: int

    def __len__(self) -> int:
        return int(self.keys.size)

    def covered_by(self, case: int) -> npt.NDArray[np.bool_]:
        """Keys of P_full in the union of C_i over the views of the case."""
        return (self.masks & np.uint64(case)) != 0

    def coverage_set(self, view: int) -> npt.NDArray[np.int64]:
        """C_i as packed keys."""
        return self.keys[(self.masks >> np.uint64(view)) & np.uint64(1) == 1]


def filter_to_ground_truth(
    refined: Sequence[npt.NDArray[np.int64]], ground_truth_keys: npt.NDArray[np.int64]
) -> list[npt.NDArray[np.int64]]:
    """P_i = P(O_i) intersected with P_gt, for every view (inputs and output sorted packed keys)."""
    return [np.intersect1d(p, ground_truth_keys, assume_unique=True) for p in refined]


def view_masks(per_view: Sequence[npt.NDArray[np.int64]]) -> tuple[npt.NDArray[np.int64], MaskArray]:
    """The union of per-view key sets and, per key, the mask of the views containing it."""
    if not per_view:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.uint64)
    everything = np.concatenate(per_view)
    views = np.repeat(np.arange(len(per_view), dtype=np.uint64), [len(k) for k in per_view])
    keys, inverse = np.unique(everything, return_inverse=True)
    masks = np.zeros(keys.size, dtype=np.uint64)
    np.bitwise_or.at(masks, inverse, np.uint64(1) << views)
    return keys, masks


def coverage_table(refined_in_gt: Sequence[npt.NDArray[np.int64]], alpha: int) -> Coverage:
    """P_full (count >= alpha) with each key's coverage mask, from the P_i."""
    keys, masks = view_masks(refined_in_gt)
    keep = popcount(masks) >= alpha
    return Coverage(keys=keys[keep], masks=masks[keep], alpha=alpha)
