"""The storage side of each label objective (`schemas.objectives`): judging a stored label and its
listed ties from a shard's arrays alone (numpy only, no solver).

A judge is built per task from a `JudgedTask` (P_full's masks recomputed from the stored P_i, and
each view's V_i on demand) and says what breaks its objective's promise for one sample's label, or
for the sets listed as equally good. That a label is the best there is needs a search:
`datagen shards validate --all`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

from schemas.config import GenerationConfig
from schemas.objectives import objective_named
from storage.samples.covers import listed_problem, mask_views
from storage.samples.visibility import key_view_masks


@dataclass(frozen=True)
class JudgedTask:
    """What a judge may read of one stored task."""

    full_masks: npt.NDArray[np.uint64]
    """P_full's keys as view masks (each key's refined views, kept when at least alpha)."""
    visible_sets: Callable[[], Sequence[npt.NDArray[np.int64]]]
    """Each view's V_i as distinct key ids, in view order (read when a judge asks)."""
    config: GenerationConfig


class LabelJudge(Protocol):
    problem_kind: str
    """The problem kind a broken label is reported under (`storage.dataset.problems`)."""

    def label_problem(self, case: int, label: int) -> str | None:
        """What breaks the objective's promise for one sample's label, or None."""
        ...

    def ties_problem(
        self, listed: npt.NDArray[np.uint64], case: int, label: int, rows: npt.NDArray[np.uint64]
    ) -> str | None:
        """What is wrong with one sample's listed ties (``rows``: the case's set-cover rows), or None."""
        ...


def task_judge(task: JudgedTask) -> LabelJudge:
    """The judge of the task's config's objective."""
    judge: LabelJudge = objective_named(task.config.label_objective).load_judge()(task)
    return judge


class CoverJudge:
    """The paper's objective: a label covers U, the P_full keys its case misses; its listed ties are
    distinct minimum covers of U of the label's size."""

    problem_kind = "uncovered"

    def __init__(self, task: JudgedTask) -> None:
        self.full_masks = task.full_masks

    def label_problem(self, case: int, label: int) -> str | None:
        universe = self.full_masks[(self.full_masks & np.uint64(case)) == 0]
        uncovered = int(np.count_nonzero((universe & np.uint64(label)) == 0))
        return f"label leaves {uncovered} keys of U uncovered" if uncovered else None

    def ties_problem(
        self, listed: npt.NDArray[np.uint64], case: int, label: int, rows: npt.NDArray[np.uint64]
    ) -> str | None:
        if rows.size and not ((rows & np.uint64(label)) != 0).all():
            return None  # the label itself does not cover U: `label_problem` names that

        def covering(sets: npt.NDArray[np.uint64]) -> str | None:
            if rows.size and not ((sets[:, None] & rows[None, :]) != 0).all():
                return "a listed minimum cover leaves keys of U uncovered"
            return None

        return listed_problem(listed, case, label, ("minimum cover", "minimum covers"), covering)


class VisibilityJudge:
    """Counts what view sets see of one task's reference (every key some view sees); the visibility
    objectives' judges build on it."""

    problem_kind = "label"

    def __init__(self, task: JudgedTask) -> None:
        self.task = task
        self.config = task.config

    @cached_property
    def masks(self) -> npt.NDArray[np.uint64]:
        return key_view_masks(self.task.visible_sets())

    @property
    def reference(self) -> int:
        """Keys some view sees."""
        return int(self.masks.size)

    def seen(self, views: int) -> int:
        """Keys of the reference the view set sees."""
        return int(np.count_nonzero((self.masks & np.uint64(views)) != 0))

    def label_problem(self, case: int, label: int) -> str | None:
        raise NotImplementedError

    def ties_problem(
        self, listed: npt.NDArray[np.uint64], case: int, label: int, rows: npt.NDArray[np.uint64] | None = None
    ) -> str | None:
        """Every listed tie sees exactly as much as the label (``rows`` are not read: these labels are
        not covers of U)."""
        seen = self.seen(case | label)

        def seeing_as_much(sets: npt.NDArray[np.uint64]) -> str | None:
            if any(self.seen(case | int(other)) != seen for other in sets.tolist()):
                return "a listed tie sees another number of keys than the label"
            return None

        return listed_problem(listed, case, label, ("tie", "ties"), seeing_as_much)


class BudgetJudge(VisibilityJudge):
    """``max_coverage``: at most ``label_budget`` views, and empty only when nothing is left unseen."""

    def label_problem(self, case: int, label: int) -> str | None:
        budget = self.config.label_budget
        if label.bit_count() > budget:
            return f"label {mask_views(label)} holds {label.bit_count()} views, more than the budget {budget}"
        unseen = self.reference - self.seen(case)
        if not label and unseen:
            return f"label is empty while the input leaves {unseen} keys unseen"
        return None


class TauJudge(VisibilityJudge):
    """``partial_cover``: the case and its label see at least ``label_tau`` of the reference."""

    def label_problem(self, case: int, label: int) -> str | None:
        need = self.config.tau_keys(self.reference)
        seen = self.seen(case | label)
        if seen < need:
            return f"input and label see {seen} of {self.reference} keys, below tau {self.config.label_tau} ({need})"
        return None


def visibility_judge(visible: Sequence[npt.NDArray[np.int64]], config: GenerationConfig) -> VisibilityJudge:
    """A counter of what view sets see of these V_i (the shared part of the visibility judges)."""
    empty = np.empty(0, dtype=np.uint64)
    return VisibilityJudge(JudgedTask(empty, lambda: visible, config))
