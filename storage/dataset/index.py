"""Opening a dataset's index: the manifest (`storage.dataset.manifest`, written by `finalise`), or in a dataset
finalised by earlier code the merged index: ``index.parquet`` (one row per sample) and ``index.json``
(the commits it covers).

Earlier code's `finalise` wrote ``index.parquet``, then ``index.json`` = {task id: attempt id} of every
commit it merged. A reader uses ``index.parquet`` only when ``index.json`` names exactly the current commit
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

from schemas.index import INDEX_SCHEMA, INDEX_SCHEMAS, CommitRecord
from storage.dataset.manifest import (
    MANIFEST_FILE,
    TASKS_SCHEMA,
    Finalised,
    being_added_to,
    check_samples_tables,
    listed_commits,
    object_of,
    read_manifest,
    read_task_samples,
    read_tasks,
    task_row,
)
from storage.dataset.manifest import finalise as finalise_manifest
from storage.dataset.sample_index import ManifestColumns, SampleIndex, from_table, from_tasks
from storage.dataset.writer import commit_path, committed_tasks, read_commit
from storage.store.location import Location, damaged, first_line
from storage.store.parquet import read_index_table

INDEX_FILE = "index.parquet"
INDEX_COVERAGE_FILE = "index.json"
NAMED_TASKS = 3
"""Tasks a reader's one-line refusal names before it says how many more there are."""

Disagreement = tuple[str, str]
"""(task id, what disagrees) for one task."""


def finalise(location: Location, commits: Sequence[CommitRecord] | None = None) -> Finalised:
    """Bring the dataset's manifest up to date with its commit records (`storage.dataset.finalise`);
    ``commits`` are every commit record when the caller read them already."""
    return finalise_manifest(location, read_schema_version(location), commits)


def read_schema_version(location: Location) -> int:
    from storage.dataset.info import read_info  # dataset_info reads the records' folders from writer

    return read_info(location).schema_version


def open_index(location: Location) -> SampleIndex:
    """Where each committed sample lives, with its index columns read on demand: from the manifest
    when there is one (and, while a job adds to the dataset, `manifest.ADDING_FILE`, the tasks
    committed since it was written), else from the legacy merged index or the fragments
    (`load_index`). `DamagedFile` for a damaged file it needs, or, while a job adds, a manifest naming
    a task without a commit record (`shards validate` names that at any time)."""
    manifest = read_manifest(location)
    if manifest is None:
        return from_table(load_index(location))
    tasks = read_tasks(location, manifest)
    check_samples_tables(location, manifest)
    schema = INDEX_SCHEMAS[manifest.schema_version]
    tail = None
    if not manifest.packed and being_added_to(location):  # a job adds tasks: they are read as they commit
        listed = listed_commits(location)
        named = tasks.column("task_id").to_pylist()
        lost = sorted(set(named) - set(listed))
        _refuse(
            location,
            MANIFEST_FILE,
            [(task, f"is in the finalised index but has no commit record ({commit_path(task)})") for task in lost],
        )
        new = sorted(set(listed) - set(named))
        if new:
            records = [_committed_record(location, task) for task in new]
            fragments = [read_fragment(location, record) for record in records]
            rows = [task_row(r, **object_of(f)) for r, f in zip(records, fragments, strict=True)]
            tasks = pa.concat_tables([tasks, pa.Table.from_pylist(rows, schema=TASKS_SCHEMA)])
            tail = pa.concat_tables(fragments).combine_chunks().cast(schema)
    return from_tasks(location, tasks, ManifestColumns(location, manifest, tail), manifest.packed)


def index_rows_of(location: Location, records: Sequence[CommitRecord], columns: list[str]) -> pa.Table:
    """``columns`` of the index rows readers serve for these tasks, and only of them: the manifest's
    row groups that hold them (fragments for tasks committed since), or an earlier datagen's index."""
    wanted = {record.task_id for record in records}
    manifest = read_manifest(location)
    if manifest is None:
        table = load_index(location)
        return table.filter(pc.is_in(table.column("task_id"), pa.array(sorted(wanted), pa.string()))).select(columns)
    tasks = read_tasks(location, manifest)
    named = set(tasks.column("task_id").to_pylist())
    found = read_task_samples(location, manifest, tasks, wanted & named, columns)
    since = [record for record in records if record.task_id not in named]
    if not since:
        return found
    return pa.concat_tables([found, merge_fragments(location, since).select(columns).cast(found.schema)])


def _committed_record(location: Location, task_id: str) -> CommitRecord:
    """A task's commit record, listed a moment ago; `DamagedFile` when it has gone since."""
    record = read_commit(location, task_id)
    if record is None:
        raise damaged(location.url, commit_path(task_id), "missing", rerun_task=True)
    return record


def load_index(location: Location, commits: Sequence[CommitRecord] | None = None) -> pa.Table:
    """The index of the committed samples, every column in memory; `DamagedFile` when the finalised
    index disagrees with the commit records or a file it needs is damaged."""
    if read_manifest(location) is not None:
        return open_index(location).table()
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
