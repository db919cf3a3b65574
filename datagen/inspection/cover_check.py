"""The ``cover`` objective's label check: each stored label against a solve of our own (docs/pipeline.md
sections 5 and 7), the `LabelChecker` that `schemas.objectives` names for it.

Every checked label must be a minimum cover and, among the minimum covers, the lexicographically
smallest tuple of views in the dataset's tie-break order (by index, or by coverage of U:
`setcover.view_order`, whose ranking is recounted here from the stored sets). The coverage is rebuilt
from the shard's stored P_i at the dataset's alpha (`label_check.full_masks`), and the expected label
is found by other means than `datagen.pipeline.setcover` (greedy and LP bounds, a MIP, a pruned
depth-first search), so a bug there cannot hide here:

- views forced by single-view rows are in every cover and are taken first;
- smaller sizes than the label's are ruled out by trying every combination of the remaining views
  (bitsets, vectorised), or by one HiGHS MIP when there are more than `label_check.SEARCH_LIMIT`;
- at the minimum size, combinations are tried in lexicographic order (`itertools.combinations`
  order) up to the label's own position: the first cover is the answer, by definition. When that
  position is too far, views are fixed in ascending order instead, each kept while a cover of the
  minimum size still exists with it (one HiGHS feasibility model per view).

A version-2 sample's listed minimum covers, their count and support are enumerated again too.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import highspy
import numpy as np
import numpy.typing as npt

from datagen.inspection.label_check import (
    COVERS_WRONG,
    HIGHS_LOCK,
    NOT_LEXICOGRAPHIC,
    NOT_MINIMUM,
    SEARCH_LIMIT,
    TIME_LIMIT,
    UNCOVERED,
    UNSOLVED,
    Ambiguity,
    MaskArray,
    SolverFailure,
    StoredSets,
    combination_chunks,
    full_masks,
    views_text,
)
from datagen.pipeline import setcover
from schemas.config import MAX_VIEWS
from storage import undominated


@dataclass(frozen=True)
class Expected:
    """The label the rules call for: the lexicographically smallest minimum cover of U."""

    size: int
    label: int


def cover_checker(stored: StoredSets) -> TaskRows:
    """The ``cover`` objective's checker: P_full's rows, every minimum cover enumerated."""
    masks = full_masks(stored.keys, stored.offsets, stored.alpha)
    return TaskRows.from_masks(masks, stored.search_limit, stored.tie_break, stored.num_views)


class TaskRows:
    """The P_full masks of one task: distinct masks with their key counts, and the undominated ones.

    For a case S, U's keys are those whose mask misses S; U's undominated masks are exactly the
    task's undominated masks that miss S (a subset of a mask missing S misses S too), so the
    reduction is done once per task.
    """

    def __init__(
        self,
        distinct: MaskArray,
        counts: npt.NDArray[np.int64],
        search_limit: int = SEARCH_LIMIT,
        tie_break: setcover.TieBreak = "index",
        num_views: int = MAX_VIEWS,
    ) -> None:
        self.distinct = distinct
        self.counts = counts
        self.undominated = undominated(distinct)
        self.search_limit = search_limit
        self.tie_break = tie_break
        self.num_views = num_views

    @classmethod
    def from_masks(
        cls,
        masks: npt.ArrayLike,
        search_limit: int = SEARCH_LIMIT,
        tie_break: setcover.TieBreak = "index",
        num_views: int = MAX_VIEWS,
    ) -> TaskRows:
        distinct, counts = np.unique(np.asarray(masks, dtype=np.uint64), return_counts=True)
        return cls(distinct, counts.astype(np.int64), search_limit, tie_break, num_views)

    def view_order(self, case: int) -> list[int] | None:
        """The tie-break's view order for case S (None: by index), from U's keys with their counts."""
        if self.tie_break == "index":
            return None
        in_universe = (self.distinct & np.uint64(case)) == 0
        counts = setcover.coverage_counts(self.distinct[in_universe], self.counts[in_universe], self.num_views)
        return setcover.view_order(counts)

    def judge(self, case: int, label: int) -> Iterator[tuple[str, str]]:
        """(kind, text) for each rule the label breaks; nothing when it is the expected label."""
        in_universe = (self.distinct & np.uint64(case)) == 0
        missed = in_universe & ((self.distinct & np.uint64(label)) == 0)
        if missed.any():
            uncovered, total = int(self.counts[missed].sum()), int(self.counts[in_universe].sum())
            yield UNCOVERED, f"label {views_text(label)} does not cover U ({uncovered} of {total} keys uncovered)"
            return
        rows = self.undominated[(self.undominated & np.uint64(case)) == 0]
        try:
            expected = expected_label(rows, label, self.search_limit, self.view_order(case))
        except SolverFailure as exc:
            yield UNSOLVED, f"label {views_text(label)} could not be checked ({exc})"
            return
        size = label.bit_count()
        if size > expected.size:
            yield NOT_MINIMUM, f"label {views_text(label)} covers U but is not minimum (k={size} > k*={expected.size})"
        elif size < expected.size:
            yield UNSOLVED, f"label {views_text(label)} covers U with k={size} < k*={expected.size}: the check is wrong"
        elif label != expected.label:
            choice = "lexicographic" if self.tie_break == "index" else f"{self.tie_break} tie-break's"
            text = f"label {views_text(label)} is minimum but not the {choice} choice {views_text(expected.label)}"
            yield NOT_LEXICOGRAPHIC, text

    def judge_covers(self, case: int, label: int, stored: Ambiguity) -> Iterator[tuple[str, str]]:
        """(kind, text) where the stored minimum covers, their count or support differ from an
        enumeration of every view set of the label's size (the label already judged minimum)."""
        rows = self.undominated[(self.undominated & np.uint64(case)) == 0]
        try:
            expected = every_minimum_cover(rows, label.bit_count(), self.search_limit)
        except SolverFailure as exc:
            yield UNSOLVED, f"minimum covers of label {views_text(label)} could not be checked ({exc})"
            return
        support = 0
        for found in expected.covers:
            support |= found
        if expected.complete:
            count, listed = len(expected.covers), set(expected.covers)
            if stored.exact and stored.count != count:
                yield COVERS_WRONG, f"the index counts {stored.count} minimum covers, there are {count}"
            elif not stored.exact and stored.count > count:
                yield COVERS_WRONG, f"the index says at least {stored.count} minimum covers, there are {count}"
            if stored.exact and set(stored.listed) != listed:
                yield COVERS_WRONG, f"the {len(stored.listed)} listed minimum covers are not the {count} that exist"
            elif not set(stored.listed) <= listed:
                yield COVERS_WRONG, "a listed cover is not a minimum cover"
        else:
            support = _support_by_highs(rows, label.bit_count())
        if stored.support != support:
            yield COVERS_WRONG, f"support {views_text(stored.support)}, the minimum covers use {views_text(support)}"


@dataclass(frozen=True)
class AllCovers:
    covers: list[int]
    """Every minimum cover found; all of them when ``complete``."""
    complete: bool


def every_minimum_cover(rows: MaskArray, size: int, search_limit: int = SEARCH_LIMIT) -> AllCovers:
    """Every cover of ``rows`` by ``size`` views (the minimum size), by trying each combination of the
    views left after the forced ones (single-view rows); incomplete past ``search_limit`` combinations."""
    if rows.size == 0:
        return AllCovers([0], True)
    singles = rows[np.bitwise_count(rows) == 1]
    forced = int(np.bitwise_or.reduce(singles)) if singles.size else 0
    rest = rows[(rows & np.uint64(forced)) == 0]
    if rest.size == 0:
        return AllCovers([forced], True)
    union = int(np.bitwise_or.reduce(rest))
    candidates = [v for v in range(union.bit_length()) if union >> v & 1]
    free = size - forced.bit_count()
    if math.comb(len(candidates), free) > search_limit:
        return AllCovers([], False)
    return AllCovers([forced | c for c in _Bitsets(rest, candidates).every(free)], True)


def _support_by_highs(rows: MaskArray, size: int) -> int:
    """Views in some cover of ``size`` views, asked of HiGHS one view at a time."""
    union = int(np.bitwise_or.reduce(rows))
    candidates = [v for v in range(union.bit_length()) if union >> v & 1]
    support = 0
    for view in candidates:
        if _min_cover_size(rows, candidates, {view: 1}, exactly=size) == size:
            support |= 1 << view
    return support


def expected_label(
    rows: MaskArray, label: int, search_limit: int = SEARCH_LIMIT, order: Sequence[int] | None = None
) -> Expected:
    """The lexicographically smallest minimum cover of ``rows`` (views compared in ``order``, by
    index when None), given ``label``, a cover, as a bound.

    Sizes below |label| are ruled out by trying every combination (or by HiGHS when there are too
    many); at the minimum size, combinations are tried in lexicographic order up to the label's own
    position (or views are fixed one at a time with HiGHS when that position is too far).
    """
    if rows.size == 0:
        return Expected(0, 0)
    if (rows == 0).any():
        raise SolverFailure("a key of U is seen by no view")
    if not bool(((rows & np.uint64(label)) != 0).all()):
        raise SolverFailure("the label does not cover U")
    singles = rows[np.bitwise_count(rows) == 1]
    forced = int(np.bitwise_or.reduce(singles)) if singles.size else 0
    rest = rows[(rows & np.uint64(forced)) == 0]
    if rest.size == 0:
        return Expected(forced.bit_count(), forced)
    union = int(np.bitwise_or.reduce(rest))
    ranking = range(union.bit_length()) if order is None else order
    candidates = [v for v in ranking if union >> v & 1]
    free = label & union  # the label's views that cover something forced views leave open
    cover = _Bitsets(rest, candidates)
    size, m = free.bit_count(), len(candidates)
    if sum(math.comb(m, j) for j in range(1, size)) <= search_limit:
        for smaller in range(1, size):
            found = cover.first(smaller, math.comb(m, smaller))
            if found is not None:
                return Expected(forced.bit_count() + smaller, forced | found)
    else:
        minimum = _min_cover_size(rest, candidates, {})
        if minimum is None:
            raise SolverFailure("HiGHS finds no cover")
        size = min(size, minimum)
    if size == free.bit_count():
        positions = [candidates.index(v) for v in candidates if free >> v & 1]
        tries = lexicographic_rank(positions, m) + 1
    else:
        tries = math.comb(m, size)
    found = cover.first(size, tries) if tries <= search_limit else None
    if found is None:
        found = _highs_lexicographic(rest, candidates, size)
    return Expected(forced.bit_count() + size, forced | found)


def lexicographic_rank(positions: Sequence[int], m: int) -> int:
    """Rank of a sorted k-combination of range(m) in lexicographic order (0 for (0, 1, .., k-1))."""
    k, rank, previous = len(positions), 0, -1
    for i, p in enumerate(positions):
        rank += sum(math.comb(m - 1 - q, k - 1 - i) for q in range(previous + 1, p))
        previous = p
    return rank


class _Bitsets:
    """For each candidate view, the rows it covers as a bitset (uint64 words): a combination covers
    every row when the OR of its views' bitsets is all ones."""

    def __init__(self, rows: MaskArray, candidates: list[int]) -> None:
        self.candidates = candidates
        incidence = ((rows[None, :] >> np.array(candidates, dtype=np.uint64)[:, None]) & np.uint64(1)).astype(bool)
        self.columns = self._pack(incidence)
        self.full = self._pack(np.ones((1, rows.size), dtype=bool))[0]

    @staticmethod
    def _pack(bits: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint64]:
        packed = np.packbits(bits, axis=1, bitorder="little")
        padded = np.zeros((packed.shape[0], -(-packed.shape[1] // 8) * 8), dtype=np.uint8)
        padded[:, : packed.shape[1]] = packed
        return padded.view(np.uint64)

    def every(self, size: int) -> list[int]:
        """Masks of every ``size``-combination that covers all rows."""
        found: list[int] = []
        for combinations in combination_chunks(len(self.candidates), size):
            covered = np.bitwise_or.reduce(self.columns[combinations], axis=1)
            for hit in np.flatnonzero((covered == self.full[None, :]).all(axis=1)).tolist():
                found.append(sum(1 << self.candidates[i] for i in combinations[hit].tolist()))
        return found

    def first(self, size: int, tries: int) -> int | None:
        """Mask of the first cover among the first ``tries`` size-combinations in lexicographic order."""
        done = 0
        for chunk in combination_chunks(len(self.candidates), size):
            combinations = chunk[: tries - done]
            covered = np.bitwise_or.reduce(self.columns[combinations], axis=1)
            hits = (covered == self.full[None, :]).all(axis=1)
            if hits.any():
                return sum(1 << self.candidates[i] for i in combinations[int(np.argmax(hits))].tolist())
            done += combinations.shape[0]
            if done >= tries:
                break
        return None


# ---------------------------------------------------------------------------------------------------------
# HiGHS, when enumeration would take too long
# ---------------------------------------------------------------------------------------------------------


def _highs_lexicographic(rows: MaskArray, candidates: list[int], size: int) -> int:
    """Views fixed in ascending order, each kept while a cover of ``size`` views remains with it."""
    fixed: dict[int, int] = {}
    taken = 0
    for view in candidates:
        if taken < size and _min_cover_size(rows, candidates, {**fixed, view: 1}, exactly=size) == size:
            fixed[view], taken = 1, taken + 1
        else:
            fixed[view] = 0
    chosen = sum(1 << v for v, x in fixed.items() if x)
    if taken != size or not bool(((rows & np.uint64(chosen)) != 0).all()):
        raise SolverFailure("the tie-break by fixing views did not end on a cover of the minimum size")
    return chosen


def _min_cover_size(
    rows: MaskArray, candidates: list[int], fixed: dict[int, int], exactly: int | None = None
) -> int | None:
    """Fewest candidate views covering every row with some views fixed (None: no such cover).

    With ``exactly`` the view count is pinned and the model is a feasibility question.
    """
    m = len(candidates)
    incidence = ((rows[:, None] >> np.array(candidates, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(bool)
    starts = np.concatenate([[0], np.cumsum(incidence.sum(axis=1))]).astype(np.int32)
    columns = np.nonzero(incidence)[1].astype(np.int32)
    values = np.ones(columns.size)
    lower_rows, upper_rows = np.ones(rows.size), np.full(rows.size, highspy.kHighsInf)
    if exactly is not None:
        starts = np.append(starts, starts[-1] + m).astype(np.int32)
        columns = np.concatenate([columns, np.arange(m, dtype=np.int32)])
        values = np.concatenate([values, np.ones(m)])
        lower_rows, upper_rows = np.append(lower_rows, exactly), np.append(upper_rows, exactly)
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = m, lower_rows.size
    lp.col_cost_ = np.zeros(m) if exactly is not None else np.ones(m)
    lp.col_lower_ = np.array([1.0 if fixed.get(v) == 1 else 0.0 for v in candidates])
    lp.col_upper_ = np.array([0.0 if fixed.get(v) == 0 else 1.0 for v in candidates])
    lp.row_lower_, lp.row_upper_ = lower_rows, upper_rows
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = starts, columns, values
    lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = m, lower_rows.size
    lp.integrality_ = [highspy.HighsVarType.kInteger] * m
    # setcover's factory: HiGHS sizes one thread pool per process, and it keeps track of that size.
    with HIGHS_LOCK:  # shards are checked on a few threads; HiGHS's scheduler is one per process
        solver = setcover.highs_solver(1, TIME_LIMIT)
        solver.passModel(lp)
        solver.run()
    status = solver.getModelStatus()
    if status == highspy.HighsModelStatus.kInfeasible:
        return None
    if status != highspy.HighsModelStatus.kOptimal:
        raise SolverFailure(f"HiGHS: {solver.modelStatusToString(status)}")
    return round(sum(solver.getSolution().col_value))
