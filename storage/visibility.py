"""What a label of a visibility objective sees, from a shard's stored V_i alone (numpy only).

The ``max_coverage`` and ``partial_cover`` objectives (docs/pipeline.md section 7.5) judge a view set
by the keys it sees of the reference, every key some view sees. A shard stores each view's V_i, so a
reader can count what any view set sees without a solver; `storage.validate` uses this to check that a
label keeps its objective's promise (its size, the share it reaches) and that its listed ties see
exactly as much. That each label is the best there is needs a search: `datagen shards validate --all`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from schemas.config import GenerationConfig
from storage.covers import listed_problem, mask_views


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


class VisibilityJudge:
    """Counts what view sets see of one task's reference."""

    def __init__(self, visible: Sequence[npt.NDArray[np.int64]], config: GenerationConfig) -> None:
        """``visible``: each view's V_i as distinct integer key ids (any packing), in view order."""
        self.config = config
        self.masks = key_view_masks(visible)

    @property
    def reference(self) -> int:
        """Keys some view sees."""
        return int(self.masks.size)

    def seen(self, views: int) -> int:
        """Keys of the reference the view set sees."""
        return int(np.count_nonzero((self.masks & np.uint64(views)) != 0))

    def label_problem(self, case: int, label: int) -> str | None:
        """What breaks the objective's promise for one sample's label, or None."""
        unseen = self.reference - self.seen(case)
        if self.config.label_objective == "max_coverage":
            budget = self.config.label_budget
            if label.bit_count() > budget:
                return f"label {mask_views(label)} holds {label.bit_count()} views, more than the budget {budget}"
            if not label and unseen:
                return f"label is empty while the input leaves {unseen} keys unseen"
            return None
        need = self.config.tau_keys(self.reference)
        seen = self.seen(case | label)
        if seen < need:
            return f"input and label see {seen} of {self.reference} keys, below tau {self.config.label_tau} ({need})"
        return None

    def ties_problem(
        self, listed: npt.NDArray[np.uint64], case: int, label: int, rows: npt.NDArray[np.uint64] | None = None
    ) -> str | None:
        """What is wrong with one sample's listed ties (every set as good as the label), or None
        (``rows``, the case's set-cover rows, are not read: these labels are not covers of U)."""
        seen = self.seen(case | label)

        def seeing_as_much(sets: npt.NDArray[np.uint64]) -> str | None:
            if any(self.seen(case | int(other)) != seen for other in sets.tolist()):
                return "a listed tie sees another number of keys than the label"
            return None

        return listed_problem(listed, case, label, ("tie", "ties"), seeing_as_much)
