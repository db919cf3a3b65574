"""Labels: minimum set covers solved exactly with HiGHS, lexicographic tie-break (docs/pipeline.md section 7).

A universe element (a key of U) is represented by the bit mask of the views that cover it. Two
facts make labels cheap:

- Only the *minimal* masks matter: a row whose view set contains another row's set is implied by
  it, and identical rows are one row. Keys with identical masks collapse too.
- For a case S, U is the set of P_full keys whose mask misses S entirely, and the minimal masks of
  U are exactly the task's minimal masks that miss S (a subset of a mask that misses S misses S
  too). So a task reduces its masks once and every case only filters that short list.

The label is found in two exact steps. First the minimum cardinality k*: a greedy cover whose
size equals the ceiling of HiGHS's LP-relaxation bound is optimal by LP duality; otherwise an exact
branch and bound (`CoverSearch`) decides, from that bound upwards, whether k views can cover every
row, and the first k that can is k*. Then the tie-break: views are tried in increasing order and a
view is kept when the remaining rows can still be covered by the remaining number of larger views,
which is by construction the lexicographically smallest minimum cover. Both searches stop at a node
budget; past it HiGHS solves the MIP with gaps 0 (k*), or a second MIP maximising
sum(2^(m-1-rank(v))) over covers of size k* (a smaller first differing view outweighs every later
one) gives the same tie-break. Views forced by single-view rows are taken first; they belong to
every cover.

The tie-break is lexicographic in a *view order*: by view index (`TIE_BREAKS` "index", the
contract's rule) or, with "coverage", views ranked by how many keys of U each one covers, most
first, ties by index (`view_order`). Every step above only walks the candidates in that order, so
both rules share one search, one MIP and one proof.

Why a search before the MIP: the covers are over at most 64 views, labels have a handful of them,
and every row's views are few, so branching on the row with the fewest views, with a packing bound
(pairwise disjoint rows each need a view of their own), settles a case in thousands of nodes. On
the hardest built-in (torus_knot_3_5: ~1,000 rows after reduction, labels of 6-7 views) HiGHS's
branch and bound took 2-14 s per case, the search 0.15 s on average (measured by a former
labels benchmark; `benchmarks/generation/label_search.py` now times the search against HiGHS).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import highspy
import numpy as np
import numpy.typing as npt

from datagen.errors import DatagenError

MaskArray = npt.NDArray[np.uint64]

TieBreak = Literal["index", "coverage"]
TIE_BREAKS: tuple[TieBreak, ...] = ("index", "coverage")
"""Which minimum cover is the label: the lexicographically smallest by view index, or by the views'
coverage of U (most keys first)."""

EXACT_WEIGHT_VIEWS = 40
"""Above this many candidate views the weighted tie-break would exceed float64's exact integers;
the tie-break then fixes views one at a time instead."""

SEARCH_NODE_BUDGET = 500_000
"""Nodes `CoverSearch` may visit for one case (size and tie-break together) before HiGHS takes
over; a count, not a time, so that which path runs never depends on the machine. The hardest
built-in needs at most ~18,000."""

HIGHS_NODE_LIMIT = 100_000
"""Branch-and-bound nodes HiGHS may spend on one model (``mip_max_nodes``): the work budget that
decides, the same on every machine, whether a case gets a label; a case past it is left out and
recorded, as on any other machine."""
HIGHS_ITERATION_LIMIT = 10_000_000
"""Simplex iterations one HiGHS solve may spend (``simplex_iteration_limit``): a count, like the nodes."""
SAFETY_NET_SECONDS = 600.0
"""The least wall-clock time a solve gets (the config's ``solver_time_limit`` may raise it): only a
safety net against a machine gone wrong, never what decides a label. Its breach fails the task
(`SolverTimeLimit`), which is run again like any failed task, so a slow or loaded machine can never
make a dataset with fewer samples."""

PACKING_ROWS = 256
"""Narrowest rows the packing bound looks at (a bound from fewer rows is weaker, never wrong)."""


class SolverTimeLimit(DatagenError):
    """A solve ran past the wall-clock safety net: the task fails loudly, naming the case, and is run
    again like any failed task; never a case left out (what the clock decides is not reproducible)."""


class LabelError(DatagenError):
    """A label could not be proven optimal within the work budgets (`HIGHS_NODE_LIMIT`, the search's
    nodes) or the solver failed: the sample is not written, on every machine alike."""


@dataclass(frozen=True)
class CoverResult:
    """The label of one case and how it was obtained."""

    label: int
    """Bit mask of the label views."""
    status: str
    """'optimal', or 'empty' when U is empty (nothing left to cover)."""
    objective: int
    """Minimum number of views (the label size)."""
    rows_before: int
    """Rows of the naive model: one per key of U."""
    rows_after: int
    """Rows after merging identical rows and dropping dominated ones."""
    seconds: float
    proof: str = "none"
    """How optimality was proven: 'forced', 'lp-bound', 'search', 'mip' ('none' for an empty U)."""
    ambiguity: CoverAmbiguity | None = None
    """Every minimum cover the label was chosen from (None when not asked for)."""

    @property
    def views(self) -> tuple[int, ...]:
        return mask_to_views(self.label)


@dataclass(frozen=True)
class CoverAmbiguity:
    """The minimum covers of one case: the label is one of them, and a planner that predicts any
    other covers just as much with just as few views.

    ``support`` is always exact. ``covers`` holds every minimum cover when ``exact``; past the cap
    (or the enumeration's node budget) it holds the label and the first others found, and ``count``
    is then a lower bound.
    """

    covers: tuple[int, ...]
    """Minimum covers as view masks, sorted as tuples of view indices; the label is always here."""
    count: int
    """How many minimum covers exist (exact when ``exact``, else a lower bound)."""
    exact: bool
    support: int
    """Mask of the views that belong to at least one minimum cover."""


def mask_to_views(mask: int) -> tuple[int, ...]:
    return tuple(i for i in range(mask.bit_length()) if mask >> i & 1)


def views_to_mask(views: tuple[int, ...] | list[int]) -> int:
    mask = 0
    for view in views:
        mask |= 1 << int(view)
    return mask


def popcount(masks: MaskArray) -> npt.NDArray[np.int64]:
    return np.bitwise_count(masks).astype(np.int64)


def minimal_masks(masks: npt.ArrayLike) -> MaskArray:
    """The distinct masks that contain no other mask, sorted (dominated and duplicate rows removed).

    Masks are taken in order of popcount; a mask is kept when no kept mask is a subset of it. Kept
    masks are few (tens to hundreds), so each level is one vectorised test against them.
    """
    unique = np.unique(np.asarray(masks, dtype=np.uint64))
    if unique.size == 0:
        return unique
    counts = popcount(unique)
    kept = np.empty(0, dtype=np.uint64)
    for level in np.unique(counts):
        candidates = unique[counts == level]
        if kept.size:
            contains_kept = ((candidates[:, None] & kept[None, :]) == kept[None, :]).any(axis=1)
            candidates = candidates[~contains_kept]
        kept = np.concatenate([kept, candidates])
    return np.sort(kept)


class TaskCover:
    """The reduced cover rows of one task (P_full's masks), ready to label any case."""

    def __init__(
        self,
        full_masks: npt.ArrayLike,
        num_views: int,
        time_limit: float = 10.0,
        tie_break: TieBreak = "index",
        cover_cap: int | None = None,
    ) -> None:
        if tie_break not in TIE_BREAKS:
            raise LabelError(f"unknown tie-break {tie_break!r}; choose one of {', '.join(TIE_BREAKS)}")
        self.full_masks = np.asarray(full_masks, dtype=np.uint64)
        self.num_views = num_views
        self.time_limit = time_limit
        self.tie_break = tie_break
        self.cover_cap = cover_cap
        """Most minimum covers listed per case (None: the labels alone, no enumeration)."""
        self.minimal = minimal_masks(self.full_masks)

    def universe_size(self, case: int) -> int:
        """|U| for case S: P_full keys covered by no view of S."""
        return int(np.count_nonzero((self.full_masks & np.uint64(case)) == 0))

    def label(self, case: int, threads: int = 1) -> CoverResult:
        """The lexicographically smallest minimum cover of U(S) in the tie-break's view order, proven optimal."""
        started = time.perf_counter()
        rows_before = self.universe_size(case)
        rows = self.minimal[(self.minimal & np.uint64(case)) == 0]
        order = self.view_order(case)
        solution = solve_cover(rows, self.num_views, self.time_limit, threads, order) if rows.size else None
        label = solution.label if solution else 0
        ambiguity = None
        if self.cover_cap is not None:
            ambiguity = minimum_covers(rows, self.num_views, label, self.cover_cap, self.time_limit, threads)
        return CoverResult(
            label=label,
            status="optimal" if rows.size else "empty",
            objective=label.bit_count(),
            rows_before=rows_before,
            rows_after=int(rows.size),
            seconds=time.perf_counter() - started,
            proof=solution.proof if solution else "none",
            ambiguity=ambiguity,
        )

    def view_order(self, case: int) -> list[int]:
        """The order the tie-break walks the views in, for case S."""
        if self.tie_break == "index":
            return list(range(self.num_views))
        universe = self.full_masks[(self.full_masks & np.uint64(case)) == 0]
        return view_order(coverage_counts(universe, None, self.num_views))


def coverage_counts(masks: npt.ArrayLike, weights: npt.ArrayLike | None, num_views: int) -> npt.NDArray[np.int64]:
    """Keys of U each view covers: for every view, the (weighted) number of masks holding its bit."""
    masks = np.asarray(masks, dtype=np.uint64)
    bits = (masks[:, None] >> np.arange(num_views, dtype=np.uint64)[None, :]) & np.uint64(1)
    if weights is None:
        return bits.sum(axis=0, dtype=np.int64)
    return (bits.astype(np.int64) * np.asarray(weights, dtype=np.int64)[:, None]).sum(axis=0)


def view_order(counts: npt.ArrayLike) -> list[int]:
    """Views by coverage, most first; equal coverage by index (the "coverage" tie-break's order)."""
    values = np.asarray(counts, dtype=np.int64)
    return sorted(range(values.size), key=lambda v: (-int(values[v]), v))


@dataclass(frozen=True)
class CoverSolution:
    label: int
    proof: str
    """How optimality was proven: 'forced' (single-view rows), 'lp-bound' (greedy meets the LP
    bound), 'search' (`CoverSearch` found no smaller cover) or 'mip' (HiGHS's branch and bound)."""


def solve_min_cover(
    rows: npt.ArrayLike,
    num_views: int,
    time_limit: float = 10.0,
    threads: int = 1,
    order: Sequence[int] | None = None,
) -> int:
    """Mask of the lexicographically smallest minimum-cardinality cover of ``rows`` (non-empty
    masks), views compared in ``order`` (default: by index). Raises `LabelError` unless optimality
    is proven."""
    return solve_cover(rows, num_views, time_limit, threads, order).label


def solve_cover(
    rows: npt.ArrayLike,
    num_views: int,
    time_limit: float = 10.0,
    threads: int = 1,
    order: Sequence[int] | None = None,
) -> CoverSolution:
    """`solve_min_cover` with the kind of optimality proof."""
    ranking = list(range(num_views)) if order is None else [int(v) for v in order]
    if sorted(ranking) != list(range(num_views)):
        raise LabelError(f"a view order must list each of the {num_views} views once")
    remaining = minimal_masks(rows)
    if (remaining == 0).any():
        raise LabelError("a key is covered by no candidate view: no cover exists")
    forced = 0
    for single in remaining[popcount(remaining) == 1].tolist():
        forced |= int(single)
    if forced:
        remaining = remaining[(remaining & np.uint64(forced)) == 0]
    if remaining.size == 0:
        return CoverSolution(forced, "forced")
    union = int(np.bitwise_or.reduce(remaining))
    candidates = [v for v in ranking if union >> v & 1]
    greedy = greedy_cover(remaining, candidates)
    bound = _lp_bound(remaining, candidates, time_limit, threads)
    search = CoverSearch(SEARCH_NODE_BUDGET)
    if greedy.bit_count() == bound:
        size, proof = greedy.bit_count(), "lp-bound"
    else:
        searched = search.minimum_size(remaining, candidates, bound, greedy.bit_count())
        if searched is not None:
            size, proof = searched, "search"
        else:
            solved = _solve(remaining, candidates, None, time_limit, threads)
            if solved is None:
                raise LabelError("HiGHS reports the cover problem infeasible")
            size, proof = solved, "mip"
    chosen = search.lexicographic(remaining, candidates, size)
    if chosen is None:
        tie_break = _fix_lexicographic if len(candidates) > EXACT_WEIGHT_VIEWS else _solve_lexicographic
        chosen = tie_break(remaining, candidates, size, time_limit, threads)
    return CoverSolution(forced | chosen, proof)


def greedy_cover(rows: MaskArray, candidates: list[int]) -> int:
    """The classic greedy cover (most rows first, ties to the lowest view): an upper bound."""
    bits = ((rows[:, None] >> np.array(candidates, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(bool)
    open_rows = np.ones(rows.size, dtype=bool)
    chosen = 0
    while open_rows.any():
        best = int(np.argmax(bits[open_rows].sum(axis=0)))
        chosen |= 1 << candidates[best]
        open_rows &= ~bits[:, best]
    return chosen


class CoverSearch:
    """Exact set-cover decisions by branch and bound over bit-mask rows, within a node budget.

    `can_cover` asks whether ``need`` views of ``allowed`` cover every row. One view of the row
    with the fewest allowed views must be chosen, so the search branches on that row's views, and
    drops each view from ``allowed`` once its branch failed (no cover left uses it). A branch is cut
    when some row has no allowed view left, or when more rows than ``need`` are pairwise disjoint
    (each needs a view of its own). Every answer is exact; `_BudgetExceeded` is raised instead of
    a guess once the budget of nodes (shared by every call on this object) is spent.
    """

    def __init__(self, node_budget: int = SEARCH_NODE_BUDGET) -> None:
        self.node_budget = node_budget
        self.nodes = 0

    def minimum_size(self, rows: MaskArray, candidates: list[int], lower: int, upper: int) -> int | None:
        """The fewest views covering ``rows``, known to lie in [lower, upper] (``upper`` is
        achieved); None when the budget runs out first."""
        allowed = views_to_mask(candidates)
        try:
            for size in range(max(lower, 1), upper):
                if self.can_cover(rows, allowed, size):
                    return size
        except _BudgetExceeded:
            return None
        return upper

    def lexicographic(self, rows: MaskArray, candidates: list[int], size: int) -> int | None:
        """The lexicographically smallest sorted tuple of ``size`` views covering every row
        (``size`` must be the minimum); None when the budget runs out first.

        Views are tried in increasing order; a view is kept when the rows it leaves uncovered can
        still be covered by the views still needed, all larger than it. The first view kept is the
        smallest that starts any minimum cover, the second the smallest that continues it, and so on.
        """
        allowed, chosen, need = views_to_mask(candidates), 0, size
        try:
            for view in candidates:
                if need == 0 or rows.size == 0:
                    break
                allowed &= ~(1 << view)
                rest = rows[(rows & np.uint64(1 << view)) == 0]
                if self.can_cover(rest, allowed, need - 1):
                    chosen, need, rows = chosen | 1 << view, need - 1, rest
        except _BudgetExceeded:
            return None
        if rows.size:
            raise LabelError(f"no cover of {size} views exists, so {size} is not the minimum")
        return chosen

    def can_cover(self, rows: MaskArray, allowed: int, need: int) -> bool:
        """Whether at most ``need`` views of the mask ``allowed`` cover every row."""
        self.nodes += 1
        if self.nodes > self.node_budget:
            raise _BudgetExceeded
        if rows.size == 0:
            return True
        if need == 0:
            return False
        rows = rows & np.uint64(allowed)
        widths = popcount(rows)
        if widths.min() == 0:
            return False
        if need == 1:
            return int(np.bitwise_and.reduce(rows)) != 0
        if _disjoint_rows(rows, widths) > need:
            return False
        branch = int(rows[int(np.argmin(widths))])
        while branch:
            view = branch & -branch
            branch ^= view
            if self.can_cover(rows[(rows & np.uint64(view)) == 0], allowed, need - 1):
                return True
            allowed &= ~view
            rows = rows & np.uint64(allowed)
            if (rows == 0).any():
                return False
        return False


ENUMERATION_NODES_PER_COVER = 64
"""Nodes the enumeration may visit per cover it may list (a count, not a time, so that which covers
are listed never depends on the machine); past it the count is a lower bound."""


def minimum_covers(
    rows: npt.ArrayLike, num_views: int, label: int, cap: int, time_limit: float = 10.0, threads: int = 1
) -> CoverAmbiguity:
    """Every minimum cover of ``rows`` (up to ``cap`` of them), their count and their support.

    ``label`` must be a minimum cover (its size is the minimum). Views forced by single-view rows
    are in every cover. The rest are enumerated by `CoverEnumerator`; when it stops early (more than
    ``cap`` covers, or its node budget spent) the support is completed view by view: v is in some
    minimum cover exactly when the rows v leaves open can be covered by k - 1 other views.
    """
    if cap < 1:
        raise LabelError(f"the cover cap must be at least 1, got {cap}")
    remaining = minimal_masks(rows)
    if remaining.size == 0:
        return CoverAmbiguity(covers=(0,), count=1, exact=True, support=0)
    if not covers(label, remaining):
        raise LabelError(f"label {mask_to_views(label)} does not cover the rows it was computed for")
    forced = 0
    for single in remaining[popcount(remaining) == 1].tolist():
        forced |= int(single)
    rest = remaining[(remaining & np.uint64(forced)) == 0]
    need = label.bit_count() - forced.bit_count()
    if rest.size == 0:
        return CoverAmbiguity(covers=(forced,), count=1, exact=True, support=forced)
    allowed = int(np.bitwise_or.reduce(rest))
    enumerator = CoverEnumerator(cap, ENUMERATION_NODES_PER_COVER * cap)
    found, exact = enumerator.covers(rest, allowed, need)
    listed = {forced | f for f in found}
    support = int(np.bitwise_or.reduce(np.asarray(sorted(listed), dtype=np.uint64)))
    if not exact:
        support |= _other_support(rest, allowed, need, support & ~forced, time_limit, threads) | forced
        keep = sorted(listed - {label}, key=mask_to_views)[: cap - 1]
        listed = {label, *keep}
    elif label not in listed:
        raise LabelError(f"label {mask_to_views(label)} is not among the minimum covers enumerated")
    ordered = tuple(sorted(listed, key=mask_to_views))
    return CoverAmbiguity(covers=ordered, count=len(found), exact=exact, support=support)


def _other_support(rows: MaskArray, allowed: int, need: int, known: int, time_limit: float, threads: int) -> int:
    """The views outside ``known`` that belong to some cover of ``need`` views of ``allowed``."""
    extra = 0
    candidates = list(mask_to_views(allowed))
    for view in mask_to_views(allowed & ~known):
        rest = rows[(rows & np.uint64(1 << view)) == 0]
        try:
            possible = CoverSearch(SEARCH_NODE_BUDGET).can_cover(rest, allowed & ~(1 << view), need - 1)
        except _BudgetExceeded:
            size = _solve(rows, candidates, {view: 1}, time_limit, threads)
            possible = size is not None and size <= need
        if possible:
            extra |= 1 << view
    return extra


class CoverEnumerator:
    """Lists every cover of ``need`` views by branch and bound, each exactly once.

    As `CoverSearch.can_cover`, it branches on the row with the fewest allowed views: some view of
    that row is in every cover, and the branch of its i-th view excludes the views before it, so
    the branches partition the covers. Only a minimum ``need`` is meaningful: every leaf where no row
    is left open is then a cover of exactly ``need`` views.
    """

    def __init__(self, cap: int, node_budget: int) -> None:
        self.cap = cap
        self.node_budget = node_budget
        self.nodes = 0
        self.found: list[int] = []

    def covers(self, rows: MaskArray, allowed: int, need: int) -> tuple[list[int], bool]:
        """(covers found, whether they are all of them). Stops after ``cap + 1`` covers, so that a
        count above the cap is told apart from one at it."""
        self.nodes, self.found = 0, []
        try:
            self._walk(rows, allowed, need, 0)
        except _BudgetExceeded:
            return self.found, False
        return self.found, True

    def _add(self, cover: int) -> None:
        self.found.append(cover)
        if len(self.found) > self.cap:
            raise _BudgetExceeded

    def _walk(self, rows: MaskArray, allowed: int, need: int, chosen: int) -> None:
        self.nodes += 1
        if self.nodes > self.node_budget:
            raise _BudgetExceeded
        if rows.size == 0:
            self._add(chosen)
            return
        if need == 0:
            return
        rows = rows & np.uint64(allowed)
        widths = popcount(rows)
        if widths.min() == 0:
            return
        if need == 1:
            common = int(np.bitwise_and.reduce(rows))
            while common:
                view = common & -common
                common ^= view
                self._add(chosen | view)
            return
        if _disjoint_rows(rows, widths) > need:
            return
        branch = int(rows[int(np.argmin(widths))])
        while branch:
            view = branch & -branch
            branch ^= view
            self._walk(rows[(rows & np.uint64(view)) == 0], allowed, need - 1, chosen | view)
            allowed &= ~view
            rows = rows & np.uint64(allowed)
            if (rows == 0).any():
                return


def _disjoint_rows(rows: MaskArray, widths: npt.NDArray[np.int64]) -> int:
    """How many pairwise disjoint rows a greedy packing finds, narrowest rows first: a lower bound
    on any cover's size."""
    narrowest = rows[np.argsort(widths, kind="stable")[:PACKING_ROWS]]
    used, count = 0, 0
    for row in narrowest.tolist():
        if not row & used:
            used |= row
            count += 1
    return count


def lexicographic_cover(
    rows: MaskArray, candidates: list[int], size: int, node_budget: int = SEARCH_NODE_BUDGET
) -> int | None:
    """`CoverSearch.lexicographic` with a budget of its own."""
    return CoverSearch(node_budget).lexicographic(rows, candidates, size)


class _BudgetExceeded(Exception):
    pass


def _lp_bound(rows: MaskArray, candidates: list[int], time_limit: float, threads: int) -> int:
    """Ceiling of the LP relaxation's optimum: a lower bound on any cover's size."""
    values = _run_model(
        rows,
        candidates,
        [1.0] * len(candidates),
        False,
        None,
        [1.0] * len(candidates),
        [0.0] * len(candidates),
        time_limit,
        threads,
        relax=True,
    )
    if values is None:
        raise LabelError("HiGHS reports the cover relaxation infeasible")
    # The tolerance may only weaken the bound (a lower bound stays valid), never strengthen it.
    return math.ceil(sum(values) - 1e-4)


def _incidence(rows: MaskArray, candidates: list[int]) -> tuple[list[int], list[int]]:
    """Row-wise CSR (starts, column indices) of which candidate views cover each row."""
    bits = ((rows[:, None] >> np.array(candidates, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(bool)
    starts = np.concatenate([[0], np.cumsum(bits.sum(axis=1))]).tolist()
    return starts, np.nonzero(bits)[1].tolist()


_scheduler_threads: list[int] = []


def highs_solver(threads: int, time_limit: float) -> highspy.Highs:
    """A HiGHS model set up for exact set cover (gaps 0, seeded, quiet); the one way to get one."""
    # HiGHS keeps one global thread pool per process, sized at its first run; a model asking for
    # another size fails ("Not Set") unless the pool is reset first.
    if _scheduler_threads and _scheduler_threads[0] != threads:
        highspy.Highs.resetGlobalScheduler(True)
        _scheduler_threads.clear()
    if not _scheduler_threads:
        _scheduler_threads.append(threads)
    solver = highspy.Highs()
    solver.setOptionValue("output_flag", False)
    solver.setOptionValue("threads", threads)
    solver.setOptionValue("time_limit", max(float(time_limit), SAFETY_NET_SECONDS))
    solver.setOptionValue("mip_max_nodes", HIGHS_NODE_LIMIT)
    solver.setOptionValue("simplex_iteration_limit", HIGHS_ITERATION_LIMIT)
    solver.setOptionValue("mip_rel_gap", 0.0)
    solver.setOptionValue("mip_abs_gap", 0.0)
    solver.setOptionValue("random_seed", 0)
    # Root-node heuristics cost more than they save on these small models (measured 1.8x).
    solver.setOptionValue("mip_heuristic_effort", 0.0)
    solver.setOptionValue("mip_heuristic_run_feasibility_jump", False)
    solver.setOptionValue("mip_heuristic_run_rins", False)
    solver.setOptionValue("mip_heuristic_run_rens", False)
    solver.setOptionValue("mip_heuristic_run_root_reduced_cost", False)
    return solver


def cover_model(
    rows: MaskArray,
    candidates: list[int],
    costs: list[float],
    *,
    maximise: bool = False,
    cardinality: int | None = None,
    lower: list[float] | None = None,
    upper: list[float] | None = None,
    relax: bool = False,
) -> highspy.HighsLp:
    """The set-cover model over ``candidates``: one column per view (bounds ``lower``..``upper``,
    default 0..1, integer unless ``relax``), one row per mask (the sum of the candidates covering it
    >= 1) and, with ``cardinality``, a row sum(x) == cardinality; the one way to build one
    (the former ``studies/labels.py`` solved it on unreduced rows as its naive baseline)."""
    m = len(candidates)
    starts, columns = _incidence(rows, candidates)
    num_rows = len(rows)
    lp = highspy.HighsLp()
    lp.num_col_ = m
    lp.col_cost_ = costs
    lp.col_lower_ = [0.0] * m if lower is None else lower
    lp.col_upper_ = [1.0] * m if upper is None else upper
    values = [1.0] * len(columns)
    row_lower = [1.0] * num_rows
    row_upper = [highspy.kHighsInf] * num_rows
    if cardinality is not None:
        starts = [*starts, starts[-1] + m]
        columns = columns + list(range(m))
        values = values + [1.0] * m
        row_lower.append(float(cardinality))
        row_upper.append(float(cardinality))
        num_rows += 1
    lp.num_row_ = num_rows
    lp.row_lower_ = row_lower
    lp.row_upper_ = row_upper
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_ = starts
    lp.a_matrix_.index_ = columns
    lp.a_matrix_.value_ = values
    lp.a_matrix_.num_col_ = m
    lp.a_matrix_.num_row_ = num_rows
    if not relax:
        lp.integrality_ = [highspy.HighsVarType.kInteger] * m
    lp.sense_ = highspy.ObjSense.kMaximize if maximise else highspy.ObjSense.kMinimize
    return lp


def _run_model(
    rows: MaskArray,
    candidates: list[int],
    costs: list[float],
    sense_maximise: bool,
    cardinality: int | None,
    upper: list[float],
    lower: list[float],
    time_limit: float,
    threads: int,
    relax: bool = False,
) -> list[float] | None:
    """Solve one binary model; None when proven infeasible, `LabelError` when not solved."""
    lp = cover_model(
        rows, candidates, costs, maximise=sense_maximise, cardinality=cardinality, lower=lower, upper=upper, relax=relax
    )
    solver = highs_solver(threads, time_limit)
    solver.passModel(lp)
    solver.run()
    status = solver.getModelStatus()
    if status == highspy.HighsModelStatus.kInfeasible:
        return None
    if status == highspy.HighsModelStatus.kTimeLimit:
        limit = float(solver.getOptionValue("time_limit")[1])
        raise SolverTimeLimit(f"HiGHS ran past the wall-clock safety net of {limit:g} s without an answer")
    if status != highspy.HighsModelStatus.kOptimal:
        raise LabelError(
            f"HiGHS did not prove optimality within its work budget ({solver.modelStatusToString(status)}; "
            f"{HIGHS_NODE_LIMIT:,} nodes)"
        )
    return list(solver.getSolution().col_value)


def _solve(
    rows: MaskArray, candidates: list[int], fixed: dict[int, int] | None, time_limit: float, threads: int
) -> int | None:
    """Minimum number of candidate views covering every row, with optional views fixed to 0 or 1
    (None when the fixing leaves no cover)."""
    fixed = fixed or {}
    lower = [1.0 if fixed.get(v) == 1 else 0.0 for v in candidates]
    upper = [0.0 if fixed.get(v) == 0 else 1.0 for v in candidates]
    values = _run_model(rows, candidates, [1.0] * len(candidates), False, None, upper, lower, time_limit, threads)
    return None if values is None else round(sum(values))


def _chosen(values: list[float], candidates: list[int]) -> int:
    return views_to_mask([v for v, x in zip(candidates, values, strict=True) if x > 0.5])


def _solve_lexicographic(rows: MaskArray, candidates: list[int], size: int, time_limit: float, threads: int) -> int:
    """Among covers of exactly ``size`` views, the lexicographically smallest sorted tuple."""
    m = len(candidates)
    weights = [float(2 ** (m - 1 - rank)) for rank in range(m)]
    values = _run_model(rows, candidates, weights, True, size, [1.0] * m, [0.0] * m, time_limit, threads)
    if values is None:
        raise LabelError("HiGHS finds no cover of the minimum size in the tie-break")
    chosen = _chosen(values, candidates)
    if chosen.bit_count() != size or not covers(chosen, rows):
        raise LabelError("the tie-break solution is not a cover of the minimum size")
    return chosen


def _fix_lexicographic(rows: MaskArray, candidates: list[int], size: int, time_limit: float, threads: int) -> int:
    """Tie-break for many views: include each view in turn whenever a minimum cover still exists."""
    fixed: dict[int, int] = {}
    taken = 0
    for view in candidates:
        if taken == size:
            fixed[view] = 0
            continue
        feasible = _solve(rows, candidates, {**fixed, view: 1}, time_limit, threads) == size
        fixed[view] = 1 if feasible else 0
        taken += fixed[view]
    return views_to_mask([v for v, x in fixed.items() if x == 1])


def covers(label: int, rows: npt.ArrayLike) -> bool:
    """Whether every row shares at least one view with the label."""
    r = np.asarray(rows, dtype=np.uint64)
    return bool(((r & np.uint64(label)) != 0).all())
