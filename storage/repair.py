"""The storage half of `datagen shards repair`: which tasks `storage.validate` finds damaged, and
withdrawing their records so that a re-run of exactly those tasks can commit again.

`resume` and a re-submit cannot mend a damaged shard: the ledger has the task done and the dataset
its commit record, so both find nothing to run. Withdrawing makes the task absent (readers then
serve the sound rest, never the damaged files); the engine half (`datagen.engine.repair`) re-runs
it and finalises the index.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from storage.file_checks import REFINALISE_FIX
from storage.index import INDEX_COVERAGE_FILE, INDEX_FILE
from storage.location import Location
from storage.writer import COMMITS, FAILURES, SHARDS, commit_path, failure_path

_TASK_FILE = re.compile(rf"^(?:{SHARDS}/(?P<shard>[^/:\s]+)/|(?:{COMMITS}|{FAILURES})/(?P<record>[^/:\s]+)\.json:)")
"""A line about a task's own file: ``shards/<task>/...`` or ``commits|failures/<task>.json:``."""
_LOST_COMMIT = re.compile(rf"^{re.escape(INDEX_COVERAGE_FILE)}: task (?P<task>\S+) is in the finalised index but has")
_INDEX_LEVEL = (f"{INDEX_FILE}:", f"{INDEX_COVERAGE_FILE}:", "index row ")


@dataclass
class Findings:
    """`storage.validate`'s problem lines sorted by what mends them."""

    tasks: dict[str, list[str]] = field(default_factory=dict)
    """task id -> its lines: re-running the task mends them (a shard, fragment or record damaged)."""
    index: list[str] = field(default_factory=list)
    """Lines finalising the index again mends (the merged index alone is stale or damaged)."""
    other: list[str] = field(default_factory=list)
    """Lines neither mends (``dataset.json`` damaged): the dataset cannot be repaired here."""

    def add_task(self, task_id: str, line: str) -> None:
        self.tasks.setdefault(task_id, []).append(line)


def sort_problems(problems: list[str]) -> Findings:
    """Each problem line to the task it names (from its file's path), the index, or neither."""
    found = Findings()
    for line in problems:
        lost = _LOST_COMMIT.match(line)
        task_file = _TASK_FILE.match(line)
        if lost:
            found.add_task(lost["task"], line)
        elif task_file and REFINALISE_FIX not in line and "duplicate sample id" not in line:
            found.add_task(task_file["shard"] or task_file["record"], line)
        elif line.startswith(_INDEX_LEVEL) or (task_file and REFINALISE_FIX in line):
            found.index.append(line)
        else:
            found.other.append(line)
    return found


def withdraw(location: Location, task_ids: list[str]) -> None:
    """Make these tasks absent: first the finalised index's record of what it covers (so readers
    merge the fragments of the remaining commits instead of refusing an index that names a missing
    task), then each task's commit and failure record. Their attempt files stay until the re-run's
    sweep removes them; no reader follows them once the commit record is gone."""
    location.remove(INDEX_COVERAGE_FILE)
    for task_id in task_ids:
        location.remove(commit_path(task_id))
        location.remove(failure_path(task_id))
