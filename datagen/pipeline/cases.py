"""Input cases: MA-SCVP's long-tail sampling (docs/pipeline.md section 6), in exact integer arithmetic.

From the visibility sets V_i: a greedy trajectory from every start view (the view with the most
new keys next, ties to the lowest index) until the union of all V_i is covered; every prefix before
full coverage is a candidate case. The number of m-view cases is proportional to G[m], the total
gain of the trajectories' (m+1)-th views: need(1) = n, need(m) = ceil(n G[m] / G[1]), capped by the
distinct candidates of size m. Candidates of each size are sorted by mask and drawn without
replacement from the task's case stream.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.coverage import view_masks
from datagen.pipeline.setcover import popcount


@dataclass(frozen=True)
class Trajectories:
    """The greedy trajectories of one task, as what the sampling needs from them."""

    gains: npt.NDArray[np.int64]
    """G[m] for m = 0..n: G[0] is the total first-view coverage, G[m] the total gain of the (m+1)-th
    views (0 for trajectories that had already ended)."""
    candidates: dict[int, list[int]]
    """Distinct candidate masks by case size, sorted."""

    def need(self, size: int, num_views: int, capped: bool = True) -> int:
        """How many cases of ``size`` views to draw."""
        if size == 1:
            return num_views
        g1 = int(self.gains[1]) if self.gains.size > 1 else 0
        if g1 == 0 or size >= self.gains.size:
            return 0
        uncapped = -((-num_views * int(self.gains[size])) // g1)
        return min(uncapped, len(self.candidates.get(size, []))) if capped else uncapped


def greedy_trajectories(visible: Sequence[npt.NDArray[np.int64]]) -> Trajectories:
    """One greedy trajectory per start view over the visibility sets (packed keys).

    Keys seen by the same views behave alike, so the search runs on distinct masks weighted by
    how many keys share them (thousands of rows instead of tens of thousands of keys).
    """
    n = len(visible)
    _, key_masks = view_masks(visible)
    masks, weights = np.unique(key_masks, return_counts=True)
    bits = ((masks[:, None] >> np.arange(n, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(np.int64)
    total = int(weights.sum())
    gains = np.zeros(n + 1, dtype=np.int64)
    candidates: dict[int, set[int]] = {}
    for start in range(n):
        chosen = 1 << start
        uncovered = weights * (bits[:, start] == 0)
        count = total - int(uncovered.sum())
        gains[0] += count
        size = 1
        while count < total:
            candidates.setdefault(size, set()).add(chosen)
            new_keys = uncovered @ bits
            best = int(np.argmax(new_keys))  # the lowest index among ties; chosen views gain 0
            chosen |= 1 << best
            uncovered = uncovered * (bits[:, best] == 0)
            gains[size] += int(new_keys[best])
            count += int(new_keys[best])
            size += 1
    return Trajectories(gains=gains, candidates={k: sorted(v) for k, v in sorted(candidates.items())})


def long_tail_cases(visible: Sequence[npt.NDArray[np.int64]], rng: np.random.Generator) -> list[int]:
    """The task's input cases as masks, ordered by (case size, mask)."""
    n = len(visible)
    trajectories = greedy_trajectories(visible)
    cases = [1 << v for v in range(n)]
    for size in range(2, n + 1):
        need = trajectories.need(size, n)
        if need == 0:
            continue
        pool = trajectories.candidates[size]
        picks = rng.choice(len(pool), size=need, replace=False)
        cases.extend(sorted(pool[i] for i in picks.tolist()))
    return sorted(cases, key=lambda mask: (mask.bit_count(), mask))


def case_sizes(cases: Sequence[int]) -> npt.NDArray[np.int64]:
    return popcount(np.asarray(cases, dtype=np.uint64))
