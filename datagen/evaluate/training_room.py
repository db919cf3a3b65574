"""The room a planner has on a dataset's own objects: the floor and the ceiling at equal views, from the
stored visibility sets alone (no mesh is read).

For each single-view case (an initial view) and budget V (views in all, the initial one included):
the floor is the better of the best fixed set of V - 1 views (`FixedPlans`, chosen on this very data:
an in-sample floor) and the spread views; the ceiling is the true gains played step by step, each
next view the one that adds the most keys some view sees, ties to the lowest index (`gain` of
`datagen evaluate`). Coverage is evaluate's: keys seen over keys some view sees, per task. What
`datagen evaluate --margins` measures on unseen meshes, here on the training objects
(`datagen shards card`). Past `MOST_TASKS` tasks a seeded sample of them is read.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from datagen.evaluate.fixed import FixedPlans, single_view_cases, spread_views, task_visibility

MOST_TASKS = 2000
"""Tasks read at most (a seeded sample of a larger dataset): the answer is a mean over cases."""


@dataclass(frozen=True)
class Room:
    """Mean coverage (percent) over the cases at one budget."""

    views: int
    cases: int
    fixed: float
    spread: float
    floor: float
    ceiling: float

    @property
    def margin(self) -> float:
        return self.ceiling - self.floor


def training_room(url: str, plans: FixedPlans, budgets: list[int], options: dict[str, Any] | None = None) -> list[Room]:
    """The floor and ceiling at each budget, over the dataset's single-view cases."""
    from storage import open_dataset

    dataset = open_dataset(url, options)
    singles = single_view_cases(dataset)
    shards = sorted(singles)
    if len(shards) > MOST_TASKS:
        chosen = np.random.default_rng(np.random.SeedSequence([len(shards), 0x600D])).choice(
            len(shards), MOST_TASKS, replace=False
        )
        shards = [shards[i] for i in sorted(chosen.tolist())]
    positions = np.asarray(dataset.info.view_positions, dtype=np.float64)
    sums = {v: np.zeros(4) for v in budgets}  # fixed, spread, floor, ceiling
    cases = 0
    for shard, masks, counts in task_visibility(dataset, shards):
        reference = int(counts.sum())
        if not reference:
            continue
        for initial in singles[shard]:
            played = _greedy_coverage(masks, counts, initial, max(budgets), dataset.num_views) / reference
            for views in budgets:
                fixed = _coverage(masks, counts, (initial, *plans.plan(views - 1, initial).views)) / reference
                spread = _coverage(masks, counts, (initial, *spread_views(positions, initial, views - 1))) / reference
                ceiling = played[min(views, len(played)) - 1]
                sums[views] += (fixed, spread, max(fixed, spread), ceiling)
            cases += 1
    return [Room(v, cases, *(100.0 * sums[v] / max(cases, 1)).tolist()) for v in budgets]


def _coverage(masks: npt.NDArray[np.uint64], counts: npt.NDArray[np.int64], views: tuple[int, ...]) -> int:
    taken = np.uint64(sum(1 << v for v in set(views)))
    return int(counts[(masks & taken) != 0].sum())


def _greedy_coverage(
    masks: npt.NDArray[np.uint64], counts: npt.NDArray[np.int64], initial: int, most: int, num_views: int
) -> npt.NDArray[np.float64]:
    """Keys seen after 1, 2, ... ``most`` views, each next view the one adding the most (lowest index
    first); it stops early, every later budget seeing all there is, when no view adds anything."""
    bits = ((masks[:, None] >> np.arange(num_views, dtype=np.uint64)) & np.uint64(1)).astype(bool)
    seen = bits[:, initial].copy()
    curve = [float(counts[seen].sum())]
    while len(curve) < most:
        gains = counts[~seen] @ bits[~seen]
        best = int(np.argmax(gains))
        if gains[best] <= 0:
            curve += [curve[-1]] * (most - len(curve))
            break
        seen |= bits[:, best]
        curve.append(float(counts[seen].sum()))
    return np.asarray(curve)
