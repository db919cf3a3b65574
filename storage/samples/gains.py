"""Every view's gain for a case, counted from the view masks of a task's keys (docs/pipeline.md
section 8.1).

A key that no view of the case holds adds one to every view in its mask. Distinct masks are counted
once per task, so a case costs one small matrix product. The generator counts the stored gains with
`MaskCounts` and `storage.validate` recounts them with it from a shard's stored sets; the tests
check both against a brute-force count over Python sets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from storage.samples.bits import mask_bits

GainArray = npt.NDArray[np.uint32]


@dataclass(frozen=True)
class MaskCounts:
    """The distinct view masks of a key set, how many keys have each, and their bits."""

    masks: npt.NDArray[np.uint64]
    counts: npt.NDArray[np.int64]
    bits: npt.NDArray[np.int64]
    """(D, n) 0/1 of each distinct mask."""

    @classmethod
    def of(cls, masks: npt.ArrayLike, views: int) -> MaskCounts:
        distinct, counts = np.unique(np.asarray(masks, dtype=np.uint64), return_counts=True)
        bits = ((distinct[:, None] >> np.arange(views, dtype=np.uint64)) & np.uint64(1)).astype(np.int64)
        return cls(masks=distinct, counts=counts.astype(np.int64), bits=bits)

    @property
    def total(self) -> int:
        """Keys counted (the denominator of the normalised gain)."""
        return int(self.counts.sum())

    def gains(self, case: int) -> GainArray:
        """(n,) keys each view would add to case ``case`` (0 for the case's own views)."""
        unseen = (self.masks & np.uint64(case)) == 0
        return (self.counts[unseen] @ self.bits[unseen]).astype(np.uint32)


def best_views(
    gains: npt.ArrayLike, cases: npt.ArrayLike, width: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(best view, views sharing its gain) of each row of ``gains`` (S, width) for the ``cases`` (S,)
    masks: the largest gain outside the case, lowest index first (the authors' first-maximum loop);
    (-1, 0) for a case of every view. The generator and every reader pick it here."""
    values = np.asarray(gains, dtype=np.int64).reshape(-1, width)
    outside = ~mask_bits(np.asarray(cases, dtype=np.uint64).reshape(-1), width)
    candidates = np.where(outside, values, -1)
    best = np.argmax(candidates, axis=1)
    top = np.take_along_axis(candidates, best[:, None], axis=1)
    ties = ((candidates == top) & outside).sum(axis=1)
    none = ~outside.any(axis=1)
    return np.where(none, -1, best).astype(np.int64), np.where(none, 0, ties).astype(np.int64)
