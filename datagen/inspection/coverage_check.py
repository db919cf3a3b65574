"""Check labels of the visibility objectives against a solve of our own (docs/pipeline.md section 7.5).

`storage.validate` only asks whether a ``max_coverage`` or ``partial_cover`` label keeps its promise
(its size, the share it reaches) and whether its listed ties see as much. Here every checked label
must also be the best there is, by other means than `datagen.pipeline.maxcover`'s search, so a bug
there cannot hide here: every combination of the allowed views is tried, smallest sizes first and each
size in lexicographic order (`itertools.combinations` order), vectorised over the task's distinct view
masks; where a size has more than the search limit of combinations, HiGHS solves the weighted maximum
coverage MIP instead and the tie-break is found by fixing views in ascending order.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import highspy
import numpy as np
import numpy.typing as npt

from datagen.inspection import label_check
from datagen.pipeline import setcover
from schemas.config import GenerationConfig

MaskArray = npt.NDArray[np.uint64]


class VisibilityRows:
    """One task's reference (every key some view sees) as distinct view masks with key counts."""

    def __init__(self, key_masks: MaskArray, config: GenerationConfig, search_limit: int) -> None:
        self.distinct, counts = np.unique(np.asarray(key_masks, dtype=np.uint64), return_counts=True)
        self.counts = counts.astype(np.int64)
        self.reference = int(self.counts.sum())
        self.config = config
        self.num_views = config.num_views
        self.search_limit = search_limit

    def seen(self, views: int) -> int:
        return int(self.counts[(self.distinct & np.uint64(views)) != 0].sum())

    def _values(self, case: int, size: int) -> tuple[list[int], npt.NDArray[np.int64]] | None:
        """Every ``size``-combination of the views outside ``case`` (as masks, lexicographic) with the keys
        case and combination see together; None past the search limit."""
        if size == 0:
            return [0], np.array([self.seen(case)], dtype=np.int64)
        candidates = [v for v in range(self.num_views) if not case >> v & 1]
        if math.comb(len(candidates), size) > self.search_limit:
            return None
        views = np.array(candidates, dtype=np.uint64)
        masks: list[int] = []
        values: list[npt.NDArray[np.int64]] = []
        for chunk in label_check.combination_chunks(len(candidates), size):
            sets = np.bitwise_or.reduce(np.uint64(1) << views[chunk], axis=1)
            sees = ((self.distinct[None, :] & (sets[:, None] | np.uint64(case))) != 0).astype(np.int64)
            values.append(sees @ self.counts)
            masks.extend(int(m) for m in sets.tolist())
        return masks, np.concatenate(values) if values else np.zeros(0, dtype=np.int64)

    def _best(self, case: int, size: int) -> int:
        """Most keys case plus ``size`` other views see (enumeration, else HiGHS)."""
        found = self._values(case, size)
        if found is not None:
            return int(found[1].max()) if found[1].size else self.seen(case)
        return _highs_max_coverage(self, case, size, {})

    def _first(self, case: int, size: int, value: int) -> int:
        """The lexicographically first ``size`` views that with case see ``value`` keys."""
        found = self._values(case, size)
        if found is not None:
            return found[0][int(np.flatnonzero(found[1] >= value)[0])]
        fixed: dict[int, int] = {}
        for view in (v for v in range(self.num_views) if not case >> v & 1):
            taken = sum(fixed.values())
            if taken < size and _highs_max_coverage(self, case, size, {**fixed, view: 1}) >= value:
                fixed[view] = 1
            else:
                fixed[view] = 0
        return sum(1 << v for v, x in fixed.items() if x)

    def expected(self, case: int) -> tuple[int, int]:
        """(size, label) the objective calls for in case S (each visibility objective's rows say)."""
        raise NotImplementedError

    def judge(self, case: int, label: int) -> Iterator[tuple[str, str]]:
        """(kind, text) for each rule the label breaks; nothing when it is the expected label."""
        text = label_check.views_text
        try:
            size, expected = self.expected(case)
        except label_check.SolverFailure as exc:
            yield label_check.UNSOLVED, f"label {text(label)} could not be checked ({exc})"
            return
        if label == expected:
            return
        seen, best = self.seen(case | label), self.seen(case | expected)
        if seen < best:
            yield label_check.NOT_MINIMUM, f"label {text(label)} sees {seen} keys, {text(expected)} sees {best}"
        elif label.bit_count() > size:
            yield (
                label_check.NOT_MINIMUM,
                f"label {text(label)} is not the fewest views (k={label.bit_count()} > {size})",
            )
        else:
            yield label_check.NOT_LEXICOGRAPHIC, f"label {text(label)} is not the lexicographic choice {text(expected)}"

    def judge_covers(self, case: int, label: int, stored: label_check.Ambiguity) -> Iterator[tuple[str, str]]:
        """(kind, text) where the stored ties, their count or support differ from an enumeration of every
        view set of the label's size (the label already judged the answer)."""
        text = label_check.views_text
        found = self._values(case, label.bit_count())
        if found is None:
            return  # too many combinations to list every tie independently; `storage.validate` checked them
        value = self.seen(case | label)
        ties = [mask for mask, seen in zip(found[0], found[1].tolist(), strict=True) if seen == value]
        support = 0
        for tie in ties:
            support |= tie
        if stored.exact and stored.count != len(ties):
            yield label_check.COVERS_WRONG, f"the index counts {stored.count} ties, there are {len(ties)}"
        elif not stored.exact and stored.count > len(ties):
            yield label_check.COVERS_WRONG, f"the index says at least {stored.count} ties, there are {len(ties)}"
        if stored.exact and set(stored.listed) != set(ties):
            yield label_check.COVERS_WRONG, f"the {len(stored.listed)} listed ties are not the {len(ties)} that exist"
        if stored.support != support:
            yield label_check.COVERS_WRONG, f"support {text(stored.support)}, the ties use {text(support)}"


def _highs_max_coverage(rows: VisibilityRows, case: int, size: int, fixed: dict[int, int]) -> int:
    """Most keys case plus exactly ``size`` other views see, some views fixed, by HiGHS's MIP:
    maximise sum(count_m y_m) with y_m <= sum of x_v over the views of mask m, sum(x) = size."""
    candidates = [v for v in range(rows.num_views) if not case >> v & 1]
    open_masks = (rows.distinct & np.uint64(case)) == 0
    masks, counts = rows.distinct[open_masks], rows.counts[open_masks]
    m, n = len(candidates), masks.size
    incidence = ((masks[:, None] >> np.array(candidates, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(bool)
    starts, columns, values = [0], [], []
    for row in range(n):  # y_m - sum x_v <= 0
        views = np.flatnonzero(incidence[row])
        columns += [m + row, *views.tolist()]
        values += [1.0, *([-1.0] * views.size)]
        starts.append(len(columns))
    columns += list(range(m))
    values += [1.0] * m
    starts.append(len(columns))
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = m + n, n + 1
    lp.col_cost_ = np.concatenate([np.zeros(m), counts.astype(float)])
    lp.sense_ = highspy.ObjSense.kMaximize
    lp.col_lower_ = np.array([1.0 if fixed.get(v) == 1 else 0.0 for v in candidates] + [0.0] * n)
    lp.col_upper_ = np.array([0.0 if fixed.get(v) == 0 else 1.0 for v in candidates] + [1.0] * n)
    lp.row_lower_ = np.concatenate([np.full(n, -highspy.kHighsInf), [size]])
    lp.row_upper_ = np.concatenate([np.zeros(n), [size]])
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_ = np.array(starts, dtype=np.int32)
    lp.a_matrix_.index_ = np.array(columns, dtype=np.int32)
    lp.a_matrix_.value_ = np.array(values)
    lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = m + n, n + 1
    lp.integrality_ = [highspy.HighsVarType.kInteger] * m + [highspy.HighsVarType.kContinuous] * n
    with label_check.HIGHS_LOCK:  # HiGHS's scheduler is one per process
        solver = setcover.highs_solver(1, label_check.TIME_LIMIT)
        solver.passModel(lp)
        solver.run()
        status = solver.getModelStatus()
        if status == highspy.HighsModelStatus.kInfeasible:
            return -1
        if status != highspy.HighsModelStatus.kOptimal:
            raise label_check.SolverFailure(f"HiGHS: {solver.modelStatusToString(status)}")
        value = solver.getInfo().objective_function_value
    return rows.seen(case) + round(value)


class BudgetRows(VisibilityRows):
    """``max_coverage``: the fewest views, at most ``label_budget``, that see the most unseen keys."""

    def expected(self, case: int) -> tuple[int, int]:
        seen = self.seen(case)
        top = min(self.config.label_budget, self.num_views - case.bit_count())
        best = self._best(case, top)
        if best == seen:
            return 0, 0
        size = next(s for s in range(1, top + 1) if self._best(case, s) == best)
        return size, self._first(case, size, best)


class TauRows(VisibilityRows):
    """``partial_cover``: the fewest views that bring what is seen to ``label_tau`` of the reference."""

    def expected(self, case: int) -> tuple[int, int]:
        need = self.config.tau_keys(self.reference)
        if self.seen(case) >= need:
            return 0, 0
        free = self.num_views - case.bit_count()
        size = next(s for s in range(1, free + 1) if self._best(case, s) >= need)
        return size, self._first(case, size, self._best(case, size))


def budget_checker(stored: label_check.StoredSets) -> BudgetRows:
    """The ``max_coverage`` objective's checker (the reference: every key some view sees)."""
    return BudgetRows(label_check.full_masks(stored.keys, stored.offsets, 1), _config(stored), stored.search_limit)


def tau_checker(stored: label_check.StoredSets) -> TauRows:
    """The ``partial_cover`` objective's checker (the reference: every key some view sees)."""
    return TauRows(label_check.full_masks(stored.keys, stored.offsets, 1), _config(stored), stored.search_limit)


def _config(stored: label_check.StoredSets) -> GenerationConfig:
    if stored.config is None:
        raise ValueError("a visibility objective's labels are checked against the dataset's config")
    return stored.config
