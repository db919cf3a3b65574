"""Which views hold each key of a family of per-view key sets (numpy only).

A shard stores each view's V_i and P_i, so a reader can count what any view set sees (the visibility
objectives' judges, `storage.samples.label_judges`) or rebuild P_full's masks without a solver.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt


def key_view_masks(per_view: Sequence[npt.NDArray[np.int64]]) -> npt.NDArray[np.uint64]:
    """For every key of the union of per-view key sets (distinct integer ids, in view order), the mask
    of the views holding it, in key order."""
    sizes = [len(keys) for keys in per_view]
    if not sum(sizes):
        return np.empty(0, dtype=np.uint64)
    views = np.repeat(np.arange(len(per_view), dtype=np.uint64), sizes)
    _, inverse = np.unique(np.concatenate(list(per_view)), return_inverse=True)
    masks = np.zeros(int(inverse.max()) + 1, dtype=np.uint64)
    np.bitwise_or.at(masks, inverse, np.uint64(1) << views)
    return masks
