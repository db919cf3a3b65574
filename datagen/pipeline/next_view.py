"""Next-best-view labels of a case (docs/pipeline.md section 8.1): every view's gain and the best one.

A view's gain is what it would add to what the case's views already have, counted two ways:

- over the visibility sets V_i (MA-SCVP's generator, the PCNBV and NBVNet labels): the keys view i
  sees that no view of S sees; normalised by every key any view sees;
- over the coverage sets C_i: the keys of P_full in C_i and in no C_s of S; normalised by |P_full|.

Both are counted from each key's view mask (`storage.samples.MaskCounts`, shared with
`storage.validate`). The best
next view (NBVNet's class) is the view outside S with the largest visibility gain, the lowest index
among equals, as the authors' first-maximum loop picks it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.coverage import view_masks
from datagen.pipeline.setcover import MaskArray
from storage.samples import GainArray, MaskCounts, best_views


@dataclass(frozen=True)
class CaseGains:
    """One case's next-view labels."""

    visible: GainArray
    """(n,) new keys of the visibility sets."""
    coverage: GainArray
    """(n,) new keys of P_full (the coverage sets)."""
    best_view: int
    best_view_ties: int
    """Views outside the case sharing the largest visibility gain (1: the best view is unique)."""


@dataclass(frozen=True)
class TaskGains:
    """Per-task counts every case's gains come from."""

    visible: MaskCounts
    coverage: MaskCounts

    @classmethod
    def of(cls, visible: Sequence[npt.NDArray[np.int64]], coverage_masks: MaskArray) -> TaskGains:
        views = len(visible)
        _, seen = view_masks(visible)
        return cls(visible=MaskCounts.of(seen, views), coverage=MaskCounts.of(coverage_masks, views))

    def case(self, case: int) -> CaseGains:
        visible = self.visible.gains(case)
        best, ties = best_views(visible[None, :], np.array([case], dtype=np.uint64), visible.shape[0])
        return CaseGains(
            visible=visible, coverage=self.coverage.gains(case), best_view=int(best[0]), best_view_ties=int(ties[0])
        )
