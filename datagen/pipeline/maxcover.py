"""Exact weighted maximum coverage over the candidate views (docs/pipeline.md section 7.5).

The labels of the ``max_coverage`` and ``partial_cover`` objectives and the fixed plans of
`datagen evaluate` ask the same question: which k views cover the most? An element is a view mask
(the views that see it) with an integer weight (how many keys share that mask, or a scaled share of
a reference); a view set covers an element when it meets the mask. For a budget k the answer is,
among the sets of at most k allowed views that cover the most weight, the one with the fewest views,
then the lexicographically smallest sorted tuple of views, so it never depends on search order.

Why a search of our own: the budgets are small (a handful of views out of at most 64), and coverage
is submodular, so the weight a set of r more views can add is at most the sum of their r largest
single gains. That bound prunes a depth-first search to a few hundred nodes on real tasks, where a
MIP would need one row per distinct mask. The search is exact; it stops at a node budget (a count,
not a time, so the result never depends on the machine) and then raises `SearchBudgetExceeded`
instead of guessing.

Two searches share the bound:

- `CoverageSearch.best`: the most weight k views can cover and every set of the fewest views that
  covers it (the answer's ties: the "covers" a dataset lists beside a label), branching on the view
  of largest gain (take it, or never take it) from a greedy answer as the first incumbent; the answer
  is the lexicographically first of the ties;
- `CoverageSearch.tied` and `reaches`: a walk in lexicographic order (views ascending) towards a
  known weight, for the rare case of more ties than the first search keeps, and for decisions
  ("can k views cover this much?").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.errors import DatagenError
from datagen.pipeline.coverage import view_masks

MaskArray = npt.NDArray[np.uint64]
Weights = npt.NDArray[np.int64]

SEARCH_NODES = 2_000_000
"""Nodes one question may visit before `SearchBudgetExceeded` (real tasks need hundreds to thousands)."""
TIES_KEPT = 4096
"""Ties the gain-ordered search keeps; past them the answer comes from the lexicographic walk."""


class SearchBudgetExceeded(DatagenError):
    """The exact search spent its node budget: the answer is not proven, so none is given."""


def visibility_masks(visible: Sequence[npt.NDArray[np.int64]]) -> tuple[MaskArray, Weights]:
    """The reference (every key some view sees, the union of the V_i) as weighted elements: each
    distinct view mask with the number of keys that have it, masks sorted."""
    distinct, counts = np.unique(view_masks(visible)[1], return_counts=True)
    return distinct, counts.astype(np.int64)


@dataclass(frozen=True)
class CoverageAnswer:
    """The answer for one budget."""

    views: int
    """Mask of the chosen views: the fewest reaching the best weight, lexicographically smallest."""
    value: int
    """Weight they cover."""


@dataclass(frozen=True)
class TiedAnswers:
    """Every set as good as the answer (same weight, same size), in lexicographic order."""

    sets: tuple[int, ...]
    """The answer first; all of them when ``exact``, else the first ones found up to the cap."""
    count: int
    """How many there are (exact when ``exact``, else a lower bound)."""
    exact: bool
    support: int
    """Views in at least one of them (always exact)."""


class CoverageSearch:
    """Weighted maximum coverage of one element set by the ``allowed`` views."""

    def __init__(
        self,
        masks: npt.ArrayLike,
        weights: npt.ArrayLike,
        num_views: int,
        allowed: int | None = None,
        node_budget: int = SEARCH_NODES,
    ) -> None:
        self.masks = np.asarray(masks, dtype=np.uint64)
        self.weights = np.asarray(weights, dtype=np.int64)
        if self.masks.shape != self.weights.shape:
            raise ValueError(f"{self.masks.shape[0]} masks but {self.weights.shape[0]} weights")
        if (self.weights < 0).any():
            raise ValueError("weights must not be negative")
        self.num_views = num_views
        every = (1 << num_views) - 1
        self.allowed = every if allowed is None else allowed & every
        self.bits = ((self.masks[:, None] >> np.arange(num_views, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(
            np.int64
        )
        self.node_budget = node_budget
        self.nodes = 0
        self._best = 0

    @property
    def total(self) -> int:
        """Weight of every element (what all views together cover, when each mask is non-empty)."""
        return int(self.weights.sum())

    def covered(self, views: int) -> int:
        """Weight the view set covers."""
        return int(self.weights[(self.masks & np.uint64(views)) != 0].sum())

    def gains(self, views: int = 0) -> Weights:
        """Weight each view would add to ``views`` (0 for views not allowed)."""
        open_rows = np.flatnonzero((self.masks & np.uint64(views)) == 0)
        gains = np.dot(self.weights[open_rows], self.bits[open_rows])
        return np.where([self.allowed >> v & 1 for v in range(self.num_views)], gains, 0).astype(np.int64)

    # -- the answer and its ties ------------------------------------------------------------------------

    def best(self, budget: int, cap: int = 1) -> tuple[CoverageAnswer, TiedAnswers]:
        """The answer for ``budget`` and its ties (up to ``cap`` listed).

        One branch and bound in gain order (take the view of largest gain, or never take it) finds the
        best weight and collects every set of the fewest views reaching it; a set is kept the first time
        it is formed. Where there are more ties than `TIES_KEPT`, the answer comes from the lexicographic
        walk instead and the support is completed view by view (`tied`).
        """
        if cap < 1:
            raise ValueError(f"the cap must be at least 1, got {cap}")
        self.nodes = 0
        rows = np.flatnonzero(self.weights > 0)
        candidates = _views(self.allowed)
        self._value, self._size = self._greedy(rows, candidates, budget)
        self._ties: list[int] = []
        self._seen: set[int] = set()
        self._more = 0
        self._keep = max(cap, TIES_KEPT) + 1
        if self._value == 0:
            return CoverageAnswer(views=0, value=0), TiedAnswers(sets=(0,), count=1, exact=True, support=0)
        self._search(rows, candidates, budget, 0, 0)
        value, size = self._value, self._size
        if self._more:
            answer = self.answer_for(value, size)
            return answer, self.tied(value, size, cap)
        ties = sorted(self._ties, key=_views)
        support = 0
        for views in ties:
            support |= views
        exact = len(ties) <= cap
        listed = tuple(ties[:cap])
        count = len(ties) if exact else cap + 1
        return CoverageAnswer(views=ties[0], value=value), TiedAnswers(listed, count, exact, support)

    def answer(self, budget: int) -> CoverageAnswer:
        """The fewest allowed views (at most ``budget``) covering the most weight, lexicographically first."""
        return self.best(budget)[0]

    def best_value(self, budget: int) -> int:
        """The most weight at most ``budget`` allowed views cover."""
        return self.best(budget)[0].value

    def reaches(self, target: int, budget: int) -> bool:
        """Whether at most ``budget`` allowed views cover ``target`` weight (a decision: stops at the first
        set that does)."""
        if target <= 0:
            return True
        self.nodes = 0
        return bool(self._walk_tied_from(np.flatnonzero(self.weights > 0), _views(self.allowed), budget, target))

    def _greedy(self, rows: npt.NDArray[np.intp], candidates: list[int], budget: int) -> tuple[int, int]:
        """Weight and size of the greedy answer (most gain first): the first incumbent."""
        value = size = 0
        for _ in range(budget):
            if not candidates or rows.size == 0:
                break
            gains = self._block_gains(rows, candidates)[1]
            best = int(np.argmax(gains))
            if gains[best] <= 0:
                break
            value += int(gains[best])
            size += 1
            rows = rows[self.bits[rows, candidates[best]] == 0]
            candidates = candidates[:best] + candidates[best + 1 :]
        return value, size

    def _record(self, chosen: int, value: int) -> None:
        size = chosen.bit_count()
        if value > self._value or (value == self._value and size < self._size):
            self._value, self._size = value, size
            self._ties, self._seen, self._more = [], set(), 0
        if value == self._value and size == self._size and chosen not in self._seen:
            self._seen.add(chosen)
            if len(self._ties) < self._keep:
                self._ties.append(chosen)
            else:
                self._more += 1

    def _hopeless(self, value: int, bound: int, size: int) -> bool:
        """No completion of a set of ``size`` views (weight ``value``) adding at most ``bound`` can be the
        answer or one of its ties."""
        return value + bound < self._value or (value + bound == self._value and size + 1 > self._size)

    def _search(self, rows: npt.NDArray[np.intp], candidates: list[int], budget: int, value: int, chosen: int) -> None:
        self._tick()
        if budget == 0 or not candidates or rows.size == 0:
            return
        block, gains = self._block_gains(rows, candidates)
        order = np.argsort(-gains, kind="stable")
        size = chosen.bit_count()
        if gains[order[0]] <= 0 or self._hopeless(
            value, _overlap_bound(self.weights[rows], block, gains, budget), size
        ):
            return
        first = int(order[0])
        view = candidates[first]
        rest = candidates[:first] + candidates[first + 1 :]
        taken, gain = chosen | 1 << view, int(gains[first])
        self._record(taken, value + gain)
        self._search(rows[self.bits[rows, view] == 0], rest, budget - 1, value + gain, taken)
        if not self._hopeless(value, _top(gains[order[1:]], budget), size):
            self._search(rows, rest, budget, value, chosen)

    # -- the lexicographic walk -------------------------------------------------------------------------

    def answer_for(self, value: int, size: int) -> CoverageAnswer:
        """The lexicographically first set of ``size`` allowed views covering ``value`` (``size`` must be
        the fewest views that can: then every set found has exactly that many)."""
        if value <= 0:
            return CoverageAnswer(views=0, value=0)
        found = self._walk_tied(value, size, cap=1, first=0)
        if not found:
            raise ValueError(f"no {size} views cover weight {value}")
        return CoverageAnswer(views=found[0], value=value)

    def tied(self, value: int, size: int, cap: int) -> TiedAnswers:
        """Every set of ``size`` allowed views covering ``value`` (the answer's ties), up to ``cap``, by a
        walk in lexicographic order; past the cap the support is completed view by view."""
        if cap < 1:
            raise ValueError(f"the cap must be at least 1, got {cap}")
        if value <= 0:
            return TiedAnswers(sets=(0,), count=1, exact=True, support=0)
        found = self._walk_tied(value, size, cap=cap + 1, first=0)
        exact = len(found) <= cap
        support = 0
        for views in found:
            support |= views
        if not exact:
            found = found[:cap]
            for view in _views(self.allowed & ~support):
                if self._walk_tied(value, size, cap=1, first=1 << view):
                    support |= 1 << view
        return TiedAnswers(sets=tuple(found), count=len(found) if exact else cap + 1, exact=exact, support=support)

    def _walk_tied(self, value: int, size: int, cap: int, first: int) -> list[int]:
        """Sets of ``size`` views holding ``first`` that cover ``value``, lexicographically, up to ``cap``."""
        self.nodes = 0
        rows = np.flatnonzero((self.weights > 0) & ((self.masks & np.uint64(first)) == 0))
        candidates = _views(self.allowed & ~first)
        return self._walk_tied_from(rows, candidates, size - first.bit_count(), value, self.covered(first), first, cap)

    def _walk_tied_from(
        self,
        rows: npt.NDArray[np.intp],
        candidates: list[int],
        budget: int,
        target: int,
        value: int = 0,
        chosen: int = 0,
        cap: int = 1,
    ) -> list[int]:
        found: list[int] = []
        self._lex(rows, candidates, budget, value, chosen, target, found, cap)
        return found

    def _lex(
        self,
        rows: npt.NDArray[np.intp],
        candidates: list[int],
        budget: int,
        value: int,
        chosen: int,
        target: int,
        found: list[int],
        cap: int,
    ) -> bool:
        """Depth-first in ascending views; True once ``cap`` sets are found (stop)."""
        self._tick()
        if value >= target:
            found.append(chosen)
            return len(found) >= cap
        if budget <= 0 or not candidates:
            return False
        block, gains = self._block_gains(rows, candidates)
        if value + _overlap_bound(self.weights[rows], block, gains, budget) < target:
            return False
        for index, view in enumerate(candidates):
            # every completion drawn from candidates[index:] adds at most their `budget` largest gains
            if value + _top(gains[index:], budget) < target:
                return False
            gain = int(gains[index])
            if gain <= 0 or value + gain + _top(gains[index + 1 :], budget - 1) < target:
                continue
            remaining = rows[self.bits[rows, view] == 0]
            taken = chosen | 1 << view
            if self._lex(remaining, candidates[index + 1 :], budget - 1, value + gain, taken, target, found, cap):
                return True
        return False

    def _block_gains(self, rows: npt.NDArray[np.intp], candidates: list[int]) -> tuple[npt.NDArray[np.int64], Weights]:
        """The open rows' incidence with the candidates, and each candidate's gain over those rows."""
        block = self.bits[rows][:, candidates]
        return block, np.dot(self.weights[rows], block)

    def _tick(self) -> None:
        self.nodes += 1
        if self.nodes > self.node_budget:
            raise SearchBudgetExceeded(
                f"the exact coverage search spent its {self.node_budget:,} nodes without a proof"
            )


def _overlap_bound(weights: Weights, block: npt.NDArray[np.int64], gains: Weights, budget: int) -> int:
    """An upper bound on the weight ``budget`` more views can add, tighter than the sum of their largest
    gains where those views overlap.

    For any share a_j in [0, 1] per element, covering adds at most the ``budget`` largest gains counted
    with weights a_j w_j, plus (1 - a_j) w_j for every element (an element is covered once, however many
    chosen views hold it: this is LP duality for the relaxation). a = 1 is the plain bound; here a_j = 0
    for the elements that two or more of the plain bound's views hold, so they count once, not twice.
    """
    plain = _top(gains, budget)
    if budget <= 1 or gains.size <= 1:
        return plain
    top = np.argsort(-gains, kind="stable")[:budget]
    shared = block[:, top].sum(axis=1) >= 2
    if not shared.any():
        return plain
    reduced = np.dot(weights * ~shared, block)
    return min(plain, _top(reduced, budget) + int(weights[shared].sum()))


def _top(gains: Weights, count: int) -> int:
    """Sum of the ``count`` largest gains (0 for none)."""
    if count <= 0 or gains.size == 0:
        return 0
    if count >= gains.size:
        return int(gains.sum())
    return int(np.partition(gains, gains.size - count)[gains.size - count :].sum())


def _views(mask: int) -> list[int]:
    return [v for v in range(mask.bit_length()) if mask >> v & 1]
