"""The floor a planner must beat: the best fixed view sets of a training dataset, and a data-free spread.

A planner that looks at the object has to do better than one that does not. The strongest plan that
does not look is one constant set of views, the same for every object, chosen once from a training
dataset: for each size c, the c views that, taken after the initial view, see the most on average
over the dataset's single-view cases (what `datagen evaluate` plays: one initial view, then the plan),
coverage counted as evaluate counts it (keys seen over keys some view sees, per task, from the stored
V_i). Where the constant set holds the run's initial view, the run takes the best c-set without it,
so every run gets c new views.

Each case weighs the same, so a key of task t with view mask m adds (keys with that mask) / |R_t|
for every single-view case of t whose view is not in m; the weights are scaled to integers (2^40 per
case) so that the exact search (`datagen.pipeline.maxcover`) compares sums without rounding. Sizes
whose search spends its node budget fall back to the greedy set, and say so.

`spread` needs no data: starting from the initial view, each next view is the candidate farthest
from every view taken so far (ties to the lowest index), a well-spread plan for any object.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from datagen.errors import PlannerError
from datagen.pipeline.keys import pack_keys
from datagen.pipeline.maxcover import CoverageAnswer, CoverageSearch, SearchBudgetExceeded, visibility_masks
from datagen.pipeline.setcover import mask_to_views
from schemas.shard import keys_array, offsets_array

if TYPE_CHECKING:
    from storage import Dataset

SCALE = 1 << 40
"""Integer weight of one whole case (a case's keys weigh 1/|R_t| each, times this), up to 4,096 tasks;
past that `case_scale` makes it smaller so that the search's sums stay in int64."""
SEARCH_HEADROOM = 1 << 57
"""Largest total weight of every case: the search adds up to 32 views' gains to a value (2^62)."""


def case_scale(tasks: int, num_views: int) -> int:
    """`SCALE`, or less where ``tasks`` of ``num_views`` single-view cases would pass `SEARCH_HEADROOM`
    (datasets of up to 4,096 tasks of 32 views keep it, and their plans)."""
    return max(1, min(SCALE, SEARCH_HEADROOM // max(1, tasks * num_views)))


NODE_BUDGET = 400_000
"""Nodes the exact search may spend on one size before the greedy set stands in."""
FIXED_OPTION = "--fixed-from"


@dataclass(frozen=True)
class FixedPlan:
    """One constant view set."""

    views: tuple[int, ...]
    mean_coverage: float
    """Mean coverage (fraction) over the training dataset's single-view cases, the initial view included."""
    exact: bool
    """Proven the best set of its size (False: the greedy set, the search spent its budget)."""


@dataclass(frozen=True)
class FixedPlans:
    """The best fixed set of every size chosen from one dataset, and the best without each initial view."""

    source: str
    tasks: int
    cases: int
    num_views: int
    by_size: dict[int, FixedPlan]
    without: dict[tuple[int, int], FixedPlan] = field(default_factory=dict)
    """(size, view) -> the best set of that size that leaves the view out (for runs starting there)."""

    def plan(self, size: int, initial_view: int) -> FixedPlan:
        """The fixed plan of ``size`` new views for a run starting at ``initial_view``."""
        size = max(0, min(size, self.num_views - 1))
        if size == 0:
            return FixedPlan((), float("nan"), True)
        chosen = self.by_size[size]
        if initial_view not in chosen.views:
            return chosen
        try:
            return self.without[(size, initial_view)]
        except KeyError:
            raise PlannerError(
                f"no fixed plan of {size} views without view {initial_view} was chosen; "
                "fixed plans are chosen for the run's initial views"
            ) from None

    def summary(self) -> list[str]:
        """Lines saying where the plans come from, how exact they are, and the first sizes' views."""
        exact = [size for size, plan in sorted(self.by_size.items()) if plan.exact]
        greedy = [size for size, plan in sorted(self.by_size.items()) if not plan.exact]
        how = f"exact for sizes {_ranges(exact)}" if exact else "no size exact"
        if greedy:
            how += f", greedy for {_ranges(greedy)} (search budget spent)"
        lines = [f"fixed plans from {self.source}: {self.tasks} tasks, {self.cases} single-view cases; {how}"]
        for size in sorted(self.by_size)[:6]:
            plan = self.by_size[size]
            views = f"{size} view{'' if size == 1 else 's'}"
            lines.append(f"  {views}: {list(plan.views)} ({100 * plan.mean_coverage:.1f} % on the training cases)")
        return lines

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "tasks": self.tasks,
            "cases": self.cases,
            "plans": {str(size): _plan_dict(p) for size, p in sorted(self.by_size.items())},
        }

    def to_record(self) -> dict[str, Any]:
        """Everything the plans hold, as plain data (`from_record` reads it back): what the cache keeps."""
        without = [[size, view, _plan_dict(p)] for (size, view), p in sorted(self.without.items())]
        return {**self.as_dict(), "num_views": self.num_views, "without": without}

    @classmethod
    def from_record(cls, data: dict[str, Any], source: str) -> FixedPlans:
        def plan(item: dict[str, Any]) -> FixedPlan:
            return FixedPlan(tuple(int(v) for v in item["views"]), float(item["mean_coverage"]), bool(item["exact"]))

        return cls(
            source=source,
            tasks=int(data["tasks"]),
            cases=int(data["cases"]),
            num_views=int(data["num_views"]),
            by_size={int(size): plan(item) for size, item in data["plans"].items()},
            without={(int(size), int(view)): plan(item) for size, view, item in data["without"]},
        )


def _plan_dict(plan: FixedPlan) -> dict[str, Any]:
    return {"views": list(plan.views), "mean_coverage": plan.mean_coverage, "exact": plan.exact}


@dataclass(frozen=True)
class CaseWeights:
    """The dataset's single-view cases as weighted view masks (see the module docstring)."""

    masks: npt.NDArray[np.uint64]
    weights: npt.NDArray[np.int64]
    initial_weight: int
    """Scaled coverage the initial views alone give, summed over the cases."""
    tasks: int
    cases: int
    num_views: int
    scale: int = SCALE
    """Weight of one whole case (`case_scale`)."""


READ_THREADS = 8
"""Shards read side by side when the visibility sets of every task are summed."""


def single_view_cases(dataset: Dataset) -> dict[str, list[int]]:
    """The dataset's single-view cases: each shard (task) with the initial views of its cases, from the
    index columns alone."""
    single = np.flatnonzero(dataset.values("case_size") == 1)
    states = dataset.values("view_state")[single].astype(np.uint64)
    owners = dataset.samples.codes[single]
    singles: dict[str, list[int]] = defaultdict(list)
    for code, state in zip(owners.tolist(), states.tolist(), strict=True):
        singles[dataset.samples.shards[code]].append(int(state).bit_length() - 1)
    return singles


def task_visibility(
    dataset: Dataset, shards: Sequence[str]
) -> Iterator[tuple[str, npt.NDArray[np.uint64], npt.NDArray[np.int64]]]:
    """(shard, its keys' distinct view masks, their key counts) of each task, from its stored V_i,
    several shards read side by side (in the given order)."""
    from storage import ShardReader

    num_views = dataset.num_views

    def visibility(shard: str) -> tuple[str, npt.NDArray[np.uint64], npt.NDArray[np.int64]]:
        reader = ShardReader(dataset.location, shard, span=dataset.samples.span(shard))
        keys, offsets = reader.array(keys_array("visible")), reader.array(offsets_array("visible"))
        packed = pack_keys(keys)
        return shard, *visibility_masks([packed[offsets[v] : offsets[v + 1]] for v in range(num_views)])

    with ThreadPoolExecutor(max_workers=READ_THREADS) as pool:
        yield from pool.map(visibility, shards)


def case_weights(url: str, storage_options: dict[str, Any] | None = None) -> CaseWeights:
    """Read every committed task's V_i and single-view cases from the dataset at ``url``."""
    from storage import open_dataset

    dataset = open_dataset(url, storage_options)
    singles = single_view_cases(dataset)
    weights: dict[int, int] = defaultdict(int)
    initial = cases = 0
    scale = case_scale(len(singles), dataset.num_views)
    for shard, masks, counts in task_visibility(dataset, sorted(singles)):  # sums do not depend on order
        initial, cases = _add_task(weights, masks, counts, singles[shard], initial, cases, scale)
    if not cases:
        raise PlannerError(f"{url}: holds no single-view cases to choose fixed plans from")
    ordered = sorted(weights)
    return CaseWeights(
        masks=np.array(ordered, dtype=np.uint64),
        weights=np.array([weights[m] for m in ordered], dtype=np.int64),
        initial_weight=initial,
        tasks=len(singles),
        cases=cases,
        num_views=dataset.num_views,
        scale=scale,
    )


def _add_task(
    weights: dict[int, int],
    masks: npt.NDArray[np.uint64],
    counts: npt.NDArray[np.int64],
    singles: list[int],
    initial: int,
    cases: int,
    scale: int = SCALE,
) -> tuple[int, int]:
    """Add one task's visibility masks and single-view cases to ``weights`` (a whole case weighing
    ``scale``); (initial, cases) after it."""
    reference = int(counts.sum())
    if not reference:
        return initial, cases
    views = np.array(singles, dtype=np.uint64)
    held = ((masks[:, None] >> views[None, :]) & np.uint64(1)).sum(axis=1).astype(np.int64)
    cases += views.size
    initial += sum(int(c) * int(h) * scale // reference for c, h in zip(counts.tolist(), held.tolist(), strict=True))
    for mask, count, inside in zip(masks.tolist(), counts.tolist(), held.tolist(), strict=True):
        missing = views.size - inside  # single-view cases of this task that do not see these keys
        if missing:
            weights[mask] += count * missing * scale // reference
    return initial, cases


def choose_fixed_plans(
    weights: CaseWeights,
    source: str,
    initial_views: tuple[int, ...] = (),
    sizes: range | None = None,
    node_budget: int = NODE_BUDGET,
) -> FixedPlans:
    """The best fixed set of every size (default 1..n-1), and for each of ``initial_views`` the best
    set of each size without it where the constant set holds it."""
    n = weights.num_views
    sizes = range(1, n) if sizes is None else sizes
    every = (1 << n) - 1

    def best(size: int, allowed: int) -> FixedPlan:
        search = CoverageSearch(weights.masks, weights.weights, n, allowed=allowed, node_budget=node_budget)
        try:
            answer, exact = search.best(size)[0], True
        except SearchBudgetExceeded:
            answer, exact = _greedy(search, size), False
        mean = (weights.initial_weight + answer.value) / (weights.scale * weights.cases)
        return FixedPlan(mask_to_views(answer.views), mean, exact)

    by_size = {size: best(size, every) for size in sizes}
    without = {
        (size, view): best(size, every & ~(1 << view))
        for size in sizes
        for view in initial_views
        if view in by_size[size].views
    }
    return FixedPlans(source, weights.tasks, weights.cases, n, by_size, without)


def _greedy(search: CoverageSearch, size: int) -> CoverageAnswer:
    chosen = value = 0
    for _ in range(size):
        gains = search.gains(chosen)
        view = int(np.argmax(gains))
        if gains[view] <= 0:
            break
        chosen |= 1 << view
        value += int(gains[view])
    return CoverageAnswer(chosen, value)


def spread_views(positions: npt.NDArray[np.float64], initial_view: int, count: int) -> tuple[int, ...]:
    """``count`` views after the initial one, each the farthest from all taken so far (ties: lowest index)."""
    points = np.asarray(positions, dtype=np.float64)
    nearest = np.linalg.norm(points - points[initial_view], axis=1)
    nearest[initial_view] = -1.0
    chosen: list[int] = []
    for _ in range(min(count, len(points) - 1)):
        view = int(np.argmax(nearest))  # argmax takes the first of equal distances
        chosen.append(view)
        nearest = np.minimum(nearest, np.linalg.norm(points - points[view], axis=1))
        nearest[[initial_view, *chosen]] = -1.0
    return tuple(chosen)


def _ranges(sizes: list[int]) -> str:
    """``[1, 2, 3, 5]`` as ``1-3, 5``."""
    parts: list[str] = []
    start = previous = None
    for size in [*sizes, None]:
        if size is not None and previous is not None and size == previous + 1:
            previous = size
            continue
        if start is not None:
            parts.append(f"{start}-{previous}" if previous != start else f"{start}")
        start = previous = size
    return ", ".join(parts)
