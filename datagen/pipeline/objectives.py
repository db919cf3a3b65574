"""The generator side of the label objectives (docs/pipeline.md sections 7 and 7.5): their labellers.

Every objective (registered once in `schemas.objectives`, which names its labeller here) turns one
task's stored sets into a `CaseLabeller`, which labels any case S with a `CoverResult` (the label
mask, how it was proven, and the sets as good as it). Generation, `relabel`, `datagen evaluate`'s
oracle and the checks all build labellers through `task_labeller`:

- ``cover`` (the paper's): the fewest views covering the keys of P_full that S misses, on the refined
  coverage sets C_i (`datagen.pipeline.setcover`);
- ``max_coverage``: the at most ``label_budget`` views that see the most of the reference (every key
  some view sees, the union of the V_i) that S has not seen;
- ``partial_cover``: the fewest views with which S sees at least ``label_tau`` of the reference, seeing
  the most among those.

The last two are judged on the visibility sets, the coverage `datagen evaluate` reports, so their
oracle is the best any planner can do at its view count; their ties go to the lowest view indices and
their listed "covers" are every set exactly as good (`datagen.pipeline.maxcover`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from datagen.pipeline.coverage import Coverage
from datagen.pipeline.maxcover import CoverageSearch, SearchBudgetExceeded, visibility_masks
from datagen.pipeline.setcover import CoverAmbiguity, CoverResult, LabelError, TaskCover
from schemas.config import GenerationConfig

PackedKeys = np.ndarray


class CaseLabeller(Protocol):
    """Labels the cases of one task."""

    def label(self, case: int, threads: int = 1) -> CoverResult: ...


LabellerFactory = Callable[[tuple[PackedKeys, ...], Coverage | None, GenerationConfig, bool], CaseLabeller]
"""(visibility sets V_i, P_full's coverage table (None where the objective does not read it: the refined
views need not exist), config, whether to list the label's ties) -> labeller."""


def task_labeller(
    visible: tuple[PackedKeys, ...], coverage: Coverage | None, config: GenerationConfig, list_covers: bool = True
) -> CaseLabeller:
    """The labeller of ``config.label_objective`` for one task."""
    factory: LabellerFactory = config.objective.load_labeller()
    return factory(visible, coverage, config, list_covers)


def cover_solver(full_masks: np.ndarray, config: GenerationConfig, list_covers: bool = True) -> TaskCover:
    """The paper's set-cover solver of one task as the config asks for it (the one place it is built);
    ``list_covers=False`` skips listing each case's minimum covers (labels alone)."""
    cap = config.label_cover_cap if list_covers else None
    return TaskCover(full_masks, config.num_views, config.solver_time_limit, config.label_tie_break, cap)


def cover_labeller(
    visible: tuple[PackedKeys, ...], coverage: Coverage | None, config: GenerationConfig, list_covers: bool
) -> CaseLabeller:
    if coverage is None:
        raise ValueError("the cover objective labels P_full's keys: give the task's coverage table")
    return cover_solver(coverage.masks, config, list_covers)


class VisibilityLabeller:
    """Labels on the visibility sets: for each case, an exact maximum coverage of what it has not seen.

    ``budget_of`` says how many views the label may hold for a case (given the search over the case's
    unseen keys, the reference size and how many keys the case has seen); 0 means the label is empty.
    """

    def __init__(
        self,
        visible: tuple[PackedKeys, ...],
        config: GenerationConfig,
        list_covers: bool,
        budget_of: Callable[[CoverageSearch, int, int], int],
    ) -> None:
        self.masks, self.weights = visibility_masks(visible)
        self.reference = int(self.weights.sum())
        self.num_views = config.num_views
        self.cap = config.label_cover_cap if list_covers else None
        self.budget_of = budget_of

    def search(self, case: int) -> CoverageSearch:
        """The maximum-coverage search of what case S has not seen, over the views outside S."""
        unseen = (self.masks & np.uint64(case)) == 0
        every = (1 << self.num_views) - 1
        return CoverageSearch(self.masks[unseen], self.weights[unseen], self.num_views, allowed=every & ~case)

    def label(self, case: int, threads: int = 1) -> CoverResult:
        started = time.perf_counter()
        search = self.search(case)
        unseen = search.total
        try:
            budget = self.budget_of(search, self.reference, self.reference - unseen) if unseen else 0
            answer, ties = search.best(budget, cap=self.cap or 1) if budget else (None, None)
        except SearchBudgetExceeded as exc:
            raise LabelError(str(exc)) from None
        label = answer.views if answer else 0
        ambiguity = None
        if self.cap is not None:
            ambiguity = (
                CoverAmbiguity(covers=ties.sets, count=ties.count, exact=ties.exact, support=ties.support)
                if ties
                else CoverAmbiguity(covers=(0,), count=1, exact=True, support=0)
            )
        return CoverResult(
            label=label,
            status="optimal" if label else "empty",
            objective=label.bit_count(),
            rows_before=unseen,
            rows_after=int(search.masks.size),
            seconds=time.perf_counter() - started,
            proof="search" if label else "none",
            ambiguity=ambiguity,
        )


def max_coverage_labeller(
    visible: tuple[PackedKeys, ...], coverage: Coverage | None, config: GenerationConfig, list_covers: bool
) -> CaseLabeller:
    budget = config.label_budget
    return VisibilityLabeller(visible, config, list_covers, lambda search, reference, seen: budget)


def partial_cover_labeller(
    visible: tuple[PackedKeys, ...], coverage: Coverage | None, config: GenerationConfig, list_covers: bool
) -> CaseLabeller:
    def views_needed(search: CoverageSearch, reference: int, seen: int) -> int:
        need = config.tau_keys(reference) - seen
        size = 0
        while need > 0 and not search.reaches(need, size):
            size += 1
        return size

    return VisibilityLabeller(visible, config, list_covers, views_needed)
