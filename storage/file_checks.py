"""The dataset-level half of `storage.validate`: do the index, the commit records and the failure
records agree, and what did interrupted writes leave behind.

Problems mean a reader refuses the dataset or serves other samples than the index promises;
warnings are harmless leftovers a user may clean up. Every problem names its file (and task) and what
mends it (`storage.problems`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import pyarrow as pa

from schemas.index import INDEX_SCHEMAS, CommitRecord, index_schema_version
from storage.index import (
    INDEX_COVERAGE_FILE,
    INDEX_FILE,
    coverage_disagreements,
    read_coverage,
    row_count_disagreements,
    unindexed_tasks,
)
from storage.location import RERUN_FIX, DamagedFile, Location, is_temporary
from storage.parquet import read_index_table, read_parquet
from storage.problems import Mend, Problem
from storage.writer import commit_path, failure_path, read_failure_records

REFINALISE_FIX = "finish the job (`datagen resume JOB`) to finalise the index again"


def check_fragments(
    location: Location, commits: Sequence[CommitRecord], schema_version: int | None
) -> tuple[list[Problem], list[pa.Table]]:
    """Problems of the committed index fragments (re-running the task mends each), and the fragments
    with the columns of the dataset's layout version (None, when dataset.json is unreadable: the first
    fragment's)."""
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
        tables.append(fragment.cast(INDEX_SCHEMAS[version]))
    return found, tables


def check_finalised_index(location: Location, commits: Sequence[CommitRecord]) -> tuple[list[Problem], pa.Table | None]:
    """Problems where ``index.json``/``index.parquet`` disagree with the commit records, and the
    finalised table when it covers exactly the commits (the index readers would use). A task the index
    names whose commit record is lost is mended by re-running it; everything else here by finalising
    the index again."""
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


def check_failures(location: Location, commits: Sequence[CommitRecord]) -> tuple[list[Problem], list[str]]:
    """(problems, warnings) of the failure records: unparsable ones are problems; a failure record
    beside a commit record is a stale leftover (see `storage.writer.write_failure`), a warning."""
    records, problems = read_failure_records(location)
    committed = {r.task_id for r in commits}
    warnings = [
        f"{failure_path(r.task_id)}: stale: task {r.task_id} is committed ({commit_path(r.task_id)}), and readers "
        "and `shards ls` follow the commit; safe to delete"
        for r in sorted(records, key=lambda r: r.task_id)
        if r.task_id in committed
    ]
    return problems, warnings


def leftover_temporaries(location: Location) -> list[str]:
    """A warning per temporary file of an interrupted write (a full disk, a killed writer)."""
    return [
        f"{relative}: leftover temporary file of an interrupted write; readers never open it; "
        "safe to delete while no job writes to this dataset"
        for relative in _files(location)
        if is_temporary(relative)
    ]


def _files(location: Location) -> Iterator[str]:
    """Every file below the root, relative to it, sorted (one recursive listing)."""
    root = location.root.strip("/")
    try:
        found = location.fs.find(location.root)
    except FileNotFoundError:
        return
    for path in sorted(str(p).strip("/") for p in found):
        yield path.removeprefix(root).strip("/")
