"""The merged index: ``index.parquet`` (one row per sample) and ``index.json`` (the commits it covers).

`finalise` writes ``index.parquet``, then ``index.json`` = {task id: attempt id} of every commit it
merged. A reader uses ``index.parquet`` only when ``index.json`` names exactly the current commit
records; when tasks were committed since (a resumed job still running), it merges their fragments
instead, as it does for a dataset never finalised.

Writers only ever add commit records, so the finalised index can never legitimately name a task
without one, name another attempt than the committed one, or hold other row counts than the
commit records' ``num_samples``. Each of those means a file was lost or replaced (by hand, a disk,
a sync tool): readers refuse such an index with one line naming the tasks, rather than serve
fewer samples than the index promises; `storage.validate` reports every disagreement.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence

import pyarrow as pa
import pyarrow.compute as pc

from schemas.index import INDEX_SCHEMA, CommitRecord
from storage.location import Location, damaged, first_line
from storage.parquet import parquet_bytes, read_index_table
from storage.writer import commit_path, committed_tasks

INDEX_FILE = "index.parquet"
INDEX_COVERAGE_FILE = "index.json"
NAMED_TASKS = 3
"""Tasks a reader's one-line refusal names before it says how many more there are."""

Disagreement = tuple[str, str]
"""(task id, what disagrees) for one task."""


def finalise(location: Location, commits: Sequence[CommitRecord] | None = None) -> pa.Table:
    """Merge the committed fragments into ``index.parquet`` (with the commits it covers); ``commits``
    are the dataset's commit records when the caller read them already."""
    commits = committed_tasks(location) if commits is None else commits
    table = merge_fragments(location, commits)
    location.write_atomic(INDEX_FILE, parquet_bytes(table))
    coverage = {r.task_id: r.attempt_id for r in commits}
    location.write_atomic(INDEX_COVERAGE_FILE, json.dumps(coverage, sort_keys=True).encode())
    return table


def load_index(location: Location, commits: Sequence[CommitRecord] | None = None) -> pa.Table:
    """The index of the committed samples; `DamagedFile` when the finalised index disagrees with
    the commit records or a file it needs is damaged."""
    commits = committed_tasks(location) if commits is None else commits
    coverage = read_coverage(location)
    if coverage is None or not location.exists(INDEX_FILE):
        return merge_fragments(location, commits)
    _refuse(location, INDEX_COVERAGE_FILE, list(coverage_disagreements(coverage, commits)))
    if coverage != {r.task_id: r.attempt_id for r in commits}:
        return merge_fragments(location, commits)  # tasks committed since finalise: not stale data
    table = read_index_table(location, INDEX_FILE)
    _refuse(location, INDEX_FILE, list(row_count_disagreements(table, commits)))
    return table


def merge_fragments(location: Location, commits: Sequence[CommitRecord]) -> pa.Table:
    """The committed tasks' index fragments, concatenated in commit (task id) order."""
    tables = [read_fragment(location, record) for record in commits]
    if not tables:
        return INDEX_SCHEMA.empty_table()
    return pa.concat_tables(tables).combine_chunks()


def read_fragment(location: Location, record: CommitRecord) -> pa.Table:
    """One task's index rows; `DamagedFile` when they are unreadable or not ``num_samples`` rows."""
    table = read_index_table(location, record.index_fragment)
    if table.num_rows != record.num_samples:
        problem = f"{table.num_rows} rows, its commit record {commit_path(record.task_id)} says {record.num_samples}"
        raise damaged(location.url, record.index_fragment, problem, rerun_task=True)
    return table


def read_coverage(location: Location) -> dict[str, str] | None:
    """``index.json``'s {task id: attempt id}; None when the dataset was never finalised."""
    try:
        data = json.loads(location.read_bytes(INDEX_COVERAGE_FILE))
    except FileNotFoundError:
        return None
    except ValueError as exc:
        raise damaged(location.url, INDEX_COVERAGE_FILE, f"unparsable ({first_line(exc)})") from None
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise damaged(location.url, INDEX_COVERAGE_FILE, "not a map of task id to attempt id")
    return data


def coverage_disagreements(coverage: dict[str, str], commits: Sequence[CommitRecord]) -> Iterator[Disagreement]:
    """Tasks ``index.json`` names that no commit record backs (or backs with another attempt)."""
    committed = {r.task_id: r.attempt_id for r in commits}
    for task_id, attempt in sorted(coverage.items()):
        if task_id not in committed:
            yield task_id, f"is in the finalised index but has no commit record ({commit_path(task_id)})"
        elif committed[task_id] != attempt:
            yield task_id, f"is in the finalised index as attempt {attempt}, committed as {committed[task_id]}"


def unindexed_tasks(coverage: dict[str, str], commits: Sequence[CommitRecord]) -> list[str]:
    """Committed tasks the finalised index does not cover (committed after `finalise` ran)."""
    return [r.task_id for r in commits if r.task_id not in coverage]


def row_count_disagreements(table: pa.Table, commits: Sequence[CommitRecord]) -> Iterator[Disagreement]:
    """Tasks whose rows in ``table`` differ from their commit record's ``num_samples``."""
    counts = task_row_counts(table)
    for record in commits:
        rows = counts.pop(record.task_id, 0)
        if rows != record.num_samples:
            yield record.task_id, f"has {rows} rows in {INDEX_FILE}, its commit record says {record.num_samples}"
    for task_id, rows in sorted(counts.items()):
        yield task_id, f"has {rows} rows in {INDEX_FILE} but no commit record ({commit_path(task_id)})"


def task_row_counts(table: pa.Table) -> dict[str, int]:
    """Rows per task id (one hash pass; pyarrow kernels outside an exec plan use no thread pool)."""
    counted = pc.value_counts(table.column("task_id"))
    return dict(zip(counted.field("values").to_pylist(), counted.field("counts").to_pylist(), strict=True))


def _refuse(location: Location, relative: str, disagreements: list[Disagreement]) -> None:
    """Raise one line naming the first tasks that disagree (none: return)."""
    if not disagreements:
        return
    shown = "; ".join(f"task {task} {what}" for task, what in disagreements[:NAMED_TASKS])
    more = len(disagreements) - NAMED_TASKS
    extra = f" (and {more} more tasks)" if more > 0 else ""
    problem = f"the finalised index disagrees with the commit records: {shown}{extra}"
    raise damaged(location.url, relative, problem, rerun_task=True)
