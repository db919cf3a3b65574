"""The storage half of `datagen shards repair`: which tasks `storage.validate` finds damaged, and
withdrawing their records so that a re-run of exactly those tasks can commit again.

`resume` and a re-submit cannot mend a damaged shard: the ledger has the task done and the dataset
its commit record, so both find nothing to run. Withdrawing makes the task absent (readers then
serve the sound rest, never the damaged files); the engine half (`datagen.engine.repair`) re-runs
it and finalises the index.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from storage.dataset.index import INDEX_COVERAGE_FILE
from storage.dataset.manifest import withdraw_tasks
from storage.dataset.problems import Mend, Problem
from storage.dataset.writer import commit_path, failure_path
from storage.store.location import Location


@dataclass
class Findings:
    """`storage.validate`'s problems sorted by what mends them (each problem's own `Mend`)."""

    tasks: dict[str, list[Problem]] = field(default_factory=dict)
    """task id -> its problems: re-running the task mends them (a shard, fragment or record damaged)."""
    index: list[Problem] = field(default_factory=list)
    """Problems finalising the index again mends (the merged index alone is stale or damaged)."""
    other: list[Problem] = field(default_factory=list)
    """Problems neither mends (``dataset.json`` damaged): the dataset cannot be repaired here."""


def sort_problems(problems: list[Problem]) -> Findings:
    """Each problem to the task whose re-run mends it, the index, or neither: from its record, never
    from its message."""
    found = Findings()
    for problem in problems:
        if problem.mend is Mend.TASK and problem.task:
            found.tasks.setdefault(problem.task, []).append(problem)
        elif problem.mend is Mend.INDEX:
            found.index.append(problem)
        else:
            found.other.append(problem)
    return found


def withdraw(location: Location, task_ids: list[str]) -> None:
    """Make these tasks absent: first from the finalised index (the manifest written again without them;
    an earlier datagen's record of what its index covers removed, so readers merge the fragments of the
    remaining commits), so that no reader meets an index naming a missing task, then each task's commit
    and failure record. Their attempt files stay until the re-run's sweep removes them; no reader
    follows them once the commit record is gone."""
    withdraw_tasks(location, task_ids)
    location.remove(INDEX_COVERAGE_FILE)
    for task_id in task_ids:
        location.remove(commit_path(task_id))
        location.remove(failure_path(task_id))
