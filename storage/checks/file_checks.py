"""The dataset-level half of `storage.validate`: do the index, the commit records and the failure
records agree, and what did interrupted writes leave behind.

Problems mean a reader refuses the dataset or serves other samples than the index promises;
warnings are harmless leftovers a user may clean up. Every problem names its file (and task) and what
mends it (`storage.dataset.problems`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from schemas.index import INDEX_SCHEMAS, CommitRecord, index_schema_version
from storage.dataset.index import (
    INDEX_COVERAGE_FILE,
    INDEX_FILE,
    coverage_disagreements,
    read_coverage,
    row_count_disagreements,
    task_row_counts,
    unindexed_tasks,
)
from storage.dataset.manifest import INDEX_FOLDER, MANIFEST_FILE, Manifest, read_manifest, read_tasks, record_of
from storage.dataset.problems import Mend, Problem
from storage.dataset.writer import COMMITS, FAILURES, SHARDS, commit_path, failure_path, read_failure_records
from storage.store.location import RERUN_FIX, DamagedFile, Location, damaged, first_line, is_temporary
from storage.store.parquet import read_index_table, read_parquet

REFINALISE_FIX = "finish the job (`datagen resume JOB`) to finalise the index again"


def check_fragments(
    location: Location, commits: Sequence[CommitRecord], schema_version: int | None, keep: bool = True
) -> tuple[list[Problem], list[pa.Table]]:
    """Problems of the committed index fragments (re-running the task mends each), and (``keep``) the
    fragments' `CHECKED_COLUMNS`, of the dataset's layout version (None, when dataset.json is unreadable:
    the first fragment's): what the row-by-row checks read when no finalised index covers the commits."""
    found: list[Problem] = []
    tables: list[pa.Table] = []
    for record in commits:

        def problem(message: str, record: CommitRecord = record) -> Problem:
            return Problem("fragment", record.index_fragment, message, Mend.TASK, record.task_id)

        try:
            fragment = read_parquet(location, record.index_fragment)
        except DamagedFile as exc:
            found.append(problem(f"cannot read index fragment ({exc.problem}); {RERUN_FIX}"))
            continue
        version = index_schema_version(fragment.schema, schema_version)
        if schema_version is None and version is not None:
            schema_version = version
        if version is None or version != schema_version:
            named = "no known version" if version is None else f"version {version}"
            found.append(problem(f"index columns of {named}, the dataset is version {schema_version}"))
            continue
        if fragment.num_rows != record.num_samples:
            found.append(problem(f"{fragment.num_rows} rows for {record.num_samples} samples"))
        if keep:
            tables.append(fragment.cast(INDEX_SCHEMAS[version]).select(list(CHECKED_COLUMNS)))
    return found, tables


def check_finalised_index(location: Location, commits: Sequence[CommitRecord]) -> tuple[list[Problem], pa.Table | None]:
    """Problems where the finalised index (the manifest, or an earlier datagen's ``index.json`` and
    ``index.parquet``) disagrees with the commit records, and its samples when it covers exactly the
    commits (the index readers would use). A task the index names whose commit record is lost is mended
    by re-running it; everything else here by finalising the index again."""
    try:
        manifest = read_manifest(location)
    except DamagedFile as exc:
        return [Problem("index", exc.relative, f"{exc.problem}; {REFINALISE_FIX}", Mend.INDEX)], None
    if manifest is not None:
        return check_manifest(location, manifest, commits)
    try:
        coverage = read_coverage(location)
    except DamagedFile as exc:
        return [Problem("index", exc.relative, f"{exc.problem}; {REFINALISE_FIX}", Mend.INDEX)], None
    if coverage is None:
        return [], None  # never finalised: readers merge the fragments (checked on their own)
    named = dict(coverage_disagreements(coverage, commits))
    committed = {r.task_id for r in commits}
    found = [  # a lost commit record: only a re-run commits the task again; another attempt: finalise again
        Problem("index", INDEX_COVERAGE_FILE, f"task {task} {what}; {RERUN_FIX}", mend, task)
        for task, what in named.items()
        for mend in [Mend.TASK if task not in committed else Mend.INDEX]
    ]
    found += [
        Problem(
            "index",
            commit_path(task),
            f"task {task} is committed but not in the finalised index ({INDEX_COVERAGE_FILE}); {REFINALISE_FIX}",
            Mend.INDEX,
            task,
        )
        for task in unindexed_tasks(coverage, commits)
    ]
    if not location.exists(INDEX_FILE):
        message = f"missing although {INDEX_COVERAGE_FILE} lists {len(coverage)} tasks"
        return [*found, Problem("index", INDEX_FILE, message, Mend.INDEX)], None
    try:
        table = read_index_table(location, INDEX_FILE)
    except DamagedFile as exc:
        return [*found, Problem("index", INDEX_FILE, f"{exc.problem}; {REFINALISE_FIX}", Mend.INDEX)], None
    covered = [r for r in commits if r.task_id in coverage]  # tasks committed since have no rows yet
    found += [
        Problem("index", INDEX_FILE, f"task {task} {what}", Mend.INDEX, task)
        for task, what in row_count_disagreements(table, covered)
        if task not in named  # one problem per lost commit record, not two
    ]
    covers_commits = coverage == {r.task_id: r.attempt_id for r in commits}
    return found, table if covers_commits else None


def check_manifest(
    location: Location, manifest: Manifest, commits: Sequence[CommitRecord]
) -> tuple[list[Problem], pa.Table | None]:
    """`check_finalised_index` of a manifest: every task it names against its commit record (there,
    the same attempt, shard and sample count), every committed task in it, and its samples tables row
    for row (each task's rows together, in shard row order, in the shard its task names)."""
    try:
        tasks = read_tasks(location, manifest)
    except DamagedFile as exc:
        return [Problem("index", exc.relative, f"{exc.problem}; {REFINALISE_FIX}", Mend.INDEX)], None
    if manifest.packed:
        committed = {row["task_id"]: record_of(row) for row in tasks.to_pylist()}
    else:
        committed = {r.task_id: r for r in commits}
    found: list[Problem] = []
    named = tasks.to_pylist()
    for row in named:
        task = row["task_id"]
        record = committed.get(task)
        if record is None:
            message = (
                f"task {task} is in the finalised index but has no commit record ({commit_path(task)}); {RERUN_FIX}"
            )
            found.append(Problem("index", MANIFEST_FILE, message, Mend.TASK, task))
            continue
        ours = (row["attempt_id"], row["shard"], row["num_samples"])
        theirs = (record.attempt_id, record.shard, record.num_samples)
        if ours != theirs:
            message = (
                f"task {task} is in the finalised index as attempt {ours[0]} ({ours[2]} samples in {ours[1]}), "
                f"committed as {theirs[0]} ({theirs[2]} samples in {theirs[1]}); {REFINALISE_FIX}"
            )
            found.append(Problem("index", MANIFEST_FILE, message, Mend.INDEX, task))
    indexed = {row["task_id"] for row in named}
    found += [
        Problem(
            "index",
            commit_path(task),
            f"task {task} is committed but not in the finalised index ({MANIFEST_FILE}); {REFINALISE_FIX}",
            Mend.INDEX,
            task,
        )
        for task in sorted(set(committed) - indexed)
    ]
    covers_commits = not found and indexed == set(committed)
    rows_found, table = _check_samples_tables(location, manifest, named)
    return found + rows_found, table if covers_commits else None


def _check_samples_tables(
    location: Location, manifest: Manifest, tasks: list[dict[str, Any]]
) -> tuple[list[Problem], pa.Table | None]:
    """Each segment's samples against its tasks: the same tasks, each's rows together and in shard row
    order, in the task's shard; the samples when all of them read."""
    found: list[Problem] = []
    tables = []
    start = 0
    unreadable = False
    for segment in manifest.segments:
        own = tasks[start : start + segment.num_tasks]
        start += segment.num_tasks
        try:
            table = read_checked_columns(location, segment.samples, manifest.schema_version)
        except DamagedFile as exc:
            found.append(Problem("index", segment.samples, f"{exc.problem}; {REFINALISE_FIX}", Mend.INDEX))
            unreadable = True
            continue
        problem = _misplaced_row(table, own)
        if problem is not None:
            task, message = problem
            found.append(Problem("index", segment.samples, f"{message}; {REFINALISE_FIX}", Mend.INDEX, task))
        if table.num_rows != sum(int(t["num_samples"]) for t in own):
            unreadable = True
            continue
        tables.append(_compact(table))
    if unreadable or not tables:
        return found, None
    # A row in the wrong place is checked row by row as well.
    return found, pa.concat_tables(tables).unify_dictionaries()


def _compact(table: pa.Table) -> pa.Table:
    """``table`` with its task and shard names dictionary-encoded: each repeats once a sample, and
    millions of samples' copies are most of what the row checks would hold."""
    for name in ("task_id", "shard"):
        table = table.set_column(table.schema.get_field_index(name), name, pc.dictionary_encode(table.column(name)))
    return table


CHECKED_COLUMNS = ("sample_id", "task_id", "shard", "row")
"""The index columns the row-by-row checks read (the others are the shards' business)."""


def read_checked_columns(location: Location, relative: str, schema_version: int) -> pa.Table:
    """`CHECKED_COLUMNS` of a samples table, read on the calling thread; `DamagedFile` when they
    cannot be read or are not the layout's."""
    schema = INDEX_SCHEMAS[schema_version]
    try:
        file = pq.ParquetFile(pa.BufferReader(location.read_bytes(relative)), pre_buffer=False)
        if index_schema_version(file.schema_arrow, schema_version) != schema_version:
            raise damaged(location.url, relative, "index columns match no known schema version")
        return file.read(columns=list(CHECKED_COLUMNS), use_threads=False).cast(
            pa.schema([schema.field(name) for name in CHECKED_COLUMNS])
        )
    except FileNotFoundError:
        raise damaged(location.url, relative, "missing") from None
    except (pa.ArrowException, ValueError, TypeError, OSError) as exc:
        raise damaged(location.url, relative, f"unreadable Parquet ({first_line(exc)})") from None


def _misplaced_row(table: pa.Table, tasks: list[dict[str, Any]]) -> tuple[str, str] | None:
    """(task, what) of the first way ``table`` differs from ``tasks``' rows (each task's samples in
    order, rows 0 to its count, in its shard); None when it holds exactly those."""
    counts = np.asarray([int(t["num_samples"]) for t in tasks], dtype=np.int64)
    if table.num_rows != int(counts.sum()):
        rows = task_row_counts(table)
        for t in tasks:
            held = rows.get(t["task_id"], 0)
            if held != t["num_samples"]:
                return t["task_id"], f"task {t['task_id']} has {held} rows, its commit record says {t['num_samples']}"
        return tasks[0]["task_id"] if tasks else "", f"{table.num_rows} rows, its tasks hold {int(counts.sum())}"
    owner = np.repeat(np.arange(len(tasks), dtype=np.int64), counts)
    wanted_row = np.arange(owner.size, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    wrong = owner != _positions(table.column("task_id"), [t["task_id"] for t in tasks])
    wrong |= owner != _positions(table.column("shard"), [t["shard"] for t in tasks])
    wrong |= table.column("row").to_numpy().astype(np.int64) != wanted_row
    if not wrong.any():
        return None
    at = int(np.flatnonzero(wrong)[0])
    task = tasks[int(owner[at])]["task_id"]
    got = (table.column("task_id")[at].as_py(), table.column("row")[at].as_py(), table.column("shard")[at].as_py())
    return task, f"row {at} is {got[0]} row {got[1]} in {got[2]}, expected {task} row {int(wanted_row[at])}"


def _positions(column: pa.ChunkedArray, names: list[str]) -> npt.NDArray[np.int64]:
    """Per row, the position of its value among ``names`` (-1 for a value not there)."""
    encoded = pc.dictionary_encode(column).combine_chunks()
    place = {name: k for k, name in enumerate(names)}
    lookup = np.asarray([place.get(v, -1) for v in encoded.dictionary.to_pylist()], dtype=np.int64)
    codes = encoded.indices.to_numpy(zero_copy_only=False).astype(np.int64)
    return lookup[codes] if lookup.size else np.full(codes.size, -1, dtype=np.int64)


def check_failures(location: Location, commits: Sequence[CommitRecord]) -> tuple[list[Problem], list[str]]:
    """(problems, warnings) of the failure records: unparsable ones are problems; a failure record
    beside a commit record is a stale leftover (see `storage.dataset.write_failure`), a warning."""
    records, problems = read_failure_records(location)
    committed = {r.task_id for r in commits}
    warnings = [
        f"{failure_path(r.task_id)}: stale: task {r.task_id} is committed ({commit_path(r.task_id)}), and readers "
        "and `shards ls` follow the commit; safe to delete"
        for r in sorted(records, key=lambda r: r.task_id)
        if r.task_id in committed
    ]
    return problems, warnings


def leftover_temporaries(location: Location, tasks: Sequence[str] | None = None) -> list[str]:
    """A warning per temporary file of an interrupted write (a full disk, a killed writer): anywhere in
    the dataset, or with ``tasks`` (a sampled validation) in the top folders and those tasks' shard
    folders only."""
    return [
        f"{relative}: leftover temporary file of an interrupted write; readers never open it; "
        "safe to delete while no job writes to this dataset"
        for relative in (_files(location) if tasks is None else _files_of(location, tasks))
        if is_temporary(relative)
    ]


def _files_of(location: Location, tasks: Sequence[str]) -> Iterator[str]:
    """The files directly in the dataset's top folders and in these tasks' shard folders, sorted."""
    folders = ["", COMMITS, FAILURES, INDEX_FOLDER, *(f"{SHARDS}/{task}" for task in tasks)]
    found = [f"{folder}/{name}" if folder else name for folder in folders for name in location.listdir(folder)]
    yield from sorted(found)


def _files(location: Location) -> Iterator[str]:
    """Every file below the root, relative to it, sorted (one recursive listing; on local disk the
    operating system's own, ten times faster than fsspec's at 300,000 files)."""
    if location.is_local:
        found = [
            os.path.relpath(os.path.join(top, name), location.root)
            for top, _, names in os.walk(location.root)
            for name in names
        ]
        yield from sorted(path.replace(os.sep, "/") for path in found)
        return
    root = location.root.strip("/")
    try:
        listed = location.fs.find(location.root)
    except FileNotFoundError:
        return
    for path in sorted(str(p).strip("/") for p in listed):
        yield path.removeprefix(root).strip("/")
