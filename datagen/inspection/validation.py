"""``datagen shards validate`` in parts that run side by side: the dataset-wide checks once, the per-task
checks (storage's of each shard, the label checks of its samples) a chunk of tasks at a time, here or
on Ray (`datagen.engine.parallel.run_each`), each chunk reading its own tasks' files and index rows only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from datagen.inspection.label_check import LabelProblem, ShardLabelCheck
from schemas.dataset import DatasetInfo
from schemas.index import CommitRecord
from storage.checks import ValidationPlan, check_tasks
from storage.dataset import Problem
from storage.store import open_location

TASK_CHUNK = 256
"""Tasks a worker checks at a time (its index rows and findings travel as one result)."""


@dataclass(frozen=True)
class ChunkFindings:
    """What checking one chunk of tasks found."""

    number: int
    """The chunk's place among the chunks (results come back in any order)."""
    tasks: int
    problems: list[Problem]
    labels: list[LabelProblem]
    checked: int
    """Labels checked with the solver."""


def task_chunks(
    plan: ValidationPlan, url: str, options: dict[str, Any], every: bool, seed: int
) -> list[tuple[Any, ...]]:
    """The arguments of `check_chunk` for each chunk of the plan's chosen tasks."""
    assert plan.info is not None
    numbers, spans = plan.numbers, plan.tasks.spans
    calls = []
    for number, start in enumerate(range(0, len(plan.chosen), TASK_CHUNK)):
        chunk = plan.chosen[start : start + TASK_CHUNK]
        own_numbers = {r.task_id: numbers[r.task_id] for r in chunk}
        own_spans = {r.shard: spans[r.shard] for r in chunk if r.shard in spans}
        calls.append((url, options, plan.info, chunk, own_numbers, own_spans, every, seed, number))
    return calls


def check_chunk(
    url: str,
    options: dict[str, Any],
    info: DatasetInfo,
    records: list[CommitRecord],
    numbers: dict[str, int],
    spans: dict[str, tuple[str, int, int]],
    every: bool,
    seed: int,
    number: int,
) -> ChunkFindings:
    """Storage's checks of these tasks' shards with the label checks as their hook (each shard read once)."""
    location = open_location(url, options)
    checker = ShardLabelCheck(location, full=every, seed=seed, records=records)
    problems = check_tasks(location, info, records, numbers, spans, every, seed, checker)
    report = checker.finish()
    return ChunkFindings(number, len(records), problems, report.problems, report.checked)
