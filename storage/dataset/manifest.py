"""The manifest: what a reader opens instead of one commit record and one index fragment per task.

``finalise`` compacts the commit log into segments under ``index/``: each segment a table of its
tasks (``tasks-<id>.parquet``: the commit records' fields, one row per task, task ids ascending)
and a table of their samples (``samples-<id>.parquet``: the index rows, each task's rows together
in shard row order, tasks in the order of the tasks table), and ``index/manifest.json`` naming the
segments in order. A job finalised again after more tasks committed (a resume, a repair) appends a
segment for those tasks only; past `MAX_SEGMENTS` they are merged into one, row group by row group.

Opening reads ``manifest.json`` and the segments' tasks tables (a few requests, whatever the task
count): a sample's shard and row follow from its task's place there, so no per-sample column is read
until asked for. The per-task commit records stay the truth: a reader lists ``commits/`` (one listing,
not a read per record) and refuses a manifest naming a task without one (a lost record); tasks
committed since the last finalise are read from their records and fragments, as before there was a
manifest. `storage.validate` compares every record with the manifest, row for row.

A packed dataset (`storage.dataset.pack`) has no commit records: its manifest is the whole truth, and each
task's row names the byte range of its shard inside a pack file.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import uuid
from collections.abc import Collection, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from pydantic import BaseModel, ConfigDict, ValidationError

from schemas.index import INDEX_SCHEMAS, CommitRecord, TaskTimings, index_schema_version
from storage.dataset.problems import Mend, Problem
from storage.dataset.writer import COMMITS, commit_path, parse_record, read_commits
from storage.store.location import DamagedFile, Location, damaged, first_line, first_validation_error
from storage.store.parquet import read_index_table, read_parquet

INDEX_FOLDER = "index"
MANIFEST_FILE = f"{INDEX_FOLDER}/manifest.json"
ADDING_FILE = f"{INDEX_FOLDER}/adding.json"
"""Present while a job may be committing tasks the manifest does not name yet (written when a job starts
on a dataset that has a manifest, removed by the `finalise` that names them): only then do readers
list ``commits/`` for them. Without it the manifest is the dataset, read without a request per 1,000
tasks (a listing of 100,000 commit records on S3 is 100 requests and seconds of parsing)."""
MANIFEST_FORMAT = 1
UNNAMED_AGE = 600.0
"""Seconds after which a segment file no manifest names is removed (see `_remove_unnamed`)."""
MAX_SEGMENTS = 16
"""Segments a manifest holds before `finalise` merges them into one."""
ROW_GROUP_TASKS = 1024
"""Tasks per row group of a samples table: about 60,000 rows, the unit a merge or a column read holds."""
READ_THREADS = 16
"""Commit records and fragments read side by side at finalise (on an object store, latency-bound)."""

TASKS_SCHEMA = pa.schema(
    [
        pa.field("task_id", pa.string(), nullable=False),
        pa.field("attempt_id", pa.string(), nullable=False),
        pa.field("shard", pa.string(), nullable=False),
        pa.field("index_fragment", pa.string(), nullable=False),
        pa.field("num_samples", pa.int64(), nullable=False),
        pa.field("schema_version", pa.int16(), nullable=False),
        pa.field("timings", pa.string(), nullable=True),
        pa.field("stored_bytes", pa.int64(), nullable=True),
        pa.field("pack", pa.string(), nullable=True),
        pa.field("pack_offset", pa.int64(), nullable=True),
        pa.field("pack_size", pa.int64(), nullable=True),
        pa.field("object_id", pa.string(), nullable=True),
        pa.field("object_name", pa.string(), nullable=True),
        pa.field("rotation", pa.int16(), nullable=True),
    ]
)
"""One row per task: its commit record (``timings`` as its JSON), the bytes its files hold when known,
for a packed dataset where its shard lies (``pack`` file, offset and size of its ZIP there), and what
its index rows say of its object (null for a task without samples): a listing of tasks or objects
reads this table, never a column of millions of samples."""


class Segment(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    tasks: str
    """Path of the tasks table, relative to the dataset root."""
    samples: str
    """Path of the samples table."""
    num_tasks: int
    num_samples: int


class Manifest(BaseModel):
    """``index/manifest.json``: the segments, in the order their samples are numbered."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: int = MANIFEST_FORMAT
    schema_version: int
    segments: list[Segment]
    packed: bool = False
    """A packed dataset: no commit records; the manifest is all there is."""

    @property
    def num_tasks(self) -> int:
        return sum(s.num_tasks for s in self.segments)

    @property
    def num_samples(self) -> int:
        return sum(s.num_samples for s in self.segments)


def read_manifest(location: Location) -> Manifest | None:
    """The manifest; None when the dataset was never finalised with one."""
    try:
        data = location.read_bytes(MANIFEST_FILE)
    except FileNotFoundError:
        return None
    try:
        return Manifest.model_validate_json(data)
    except ValidationError as exc:
        raise damaged(location.url, MANIFEST_FILE, f"unparsable ({first_validation_error(exc)})") from None


def read_tasks(location: Location, manifest: Manifest) -> pa.Table:
    """Every task of the manifest (`TASKS_SCHEMA`), in sample order; `DamagedFile` naming a damaged table."""
    tables = []
    for segment in manifest.segments:
        table = read_parquet(location, segment.tasks)
        for field in TASKS_SCHEMA:  # a column added since the table was written: unknown (null)
            if field.nullable and field.name not in table.column_names:
                table = table.append_column(field, pa.nulls(table.num_rows, field.type))
        try:
            table = table.select(TASKS_SCHEMA.names).cast(TASKS_SCHEMA)
        except (KeyError, pa.ArrowException, ValueError) as exc:
            raise damaged(location.url, segment.tasks, f"unreadable tasks table ({first_line(exc)})") from None
        if table.num_rows != segment.num_tasks:
            problem = f"{table.num_rows} tasks, {MANIFEST_FILE} says {segment.num_tasks}"
            raise damaged(location.url, segment.tasks, problem)
        total = int(pc.sum(table.column("num_samples")).as_py() or 0)
        if total != segment.num_samples:
            problem = f"its tasks hold {total} samples, {MANIFEST_FILE} says {segment.num_samples}"
            raise damaged(location.url, segment.tasks, problem)
        tables.append(table)
    return pa.concat_tables(tables) if tables else TASKS_SCHEMA.empty_table()


def check_samples_tables(location: Location, manifest: Manifest) -> None:
    """Each samples table holds the rows its segment promises (its footer only); `DamagedFile` otherwise."""
    for segment in manifest.segments:
        rows = samples_file(location, segment).metadata.num_rows
        if rows != segment.num_samples:
            raise damaged(location.url, segment.samples, f"{rows} rows, {MANIFEST_FILE} says {segment.num_samples}")


def samples_file(location: Location, segment: Segment) -> pq.ParquetFile:
    """A segment's samples table, opened for reading columns (local: memory-mapped; an object store:
    ranged reads); `DamagedFile` when it is missing or not Parquet."""
    try:
        if location.is_local:
            source: Any = pa.memory_map(location.path(segment.samples))
        else:
            source = location.fs.open(location.path(segment.samples), "rb")
        return pq.ParquetFile(source, pre_buffer=False)
    except FileNotFoundError:
        raise damaged(location.url, segment.samples, "missing") from None
    except (pa.ArrowException, ValueError, OSError) as exc:
        raise damaged(location.url, segment.samples, f"unreadable Parquet ({first_line(exc)})") from None


def read_samples_column(location: Location, manifest: Manifest, name: str) -> pa.ChunkedArray:
    """One index column of every segment, in sample order, read on the calling thread."""
    chunks: list[pa.Array] = []
    for segment in manifest.segments:
        file = samples_file(location, segment)
        try:
            column = file.read(columns=[name], use_threads=False).column(0)
        except (pa.ArrowException, ValueError, OSError, KeyError) as exc:
            raise damaged(location.url, segment.samples, f"unreadable column {name} ({first_line(exc)})") from None
        if len(column) != segment.num_samples:
            problem = f"{len(column)} rows, {MANIFEST_FILE} says {segment.num_samples}"
            raise damaged(location.url, segment.samples, problem)
        chunks.extend(column.chunks)
    schema = INDEX_SCHEMAS[manifest.schema_version]
    return pa.chunked_array(chunks, type=schema.field(name).type)


def read_samples_group(
    location: Location, manifest: Manifest, position: int, name: str
) -> tuple[tuple[int, int], pa.Array] | None:
    """Column ``name`` of the row group holding row ``position``, with that group's (first, end) rows;
    None past the manifest's rows."""
    offset = 0
    for segment in manifest.segments:
        if position >= offset + segment.num_samples:
            offset += segment.num_samples
            continue
        file = samples_file(location, segment)
        start = offset
        for group in range(file.num_row_groups):
            rows = file.metadata.row_group(group).num_rows
            if position < start + rows:
                values = file.read_row_group(group, columns=[name], use_threads=False).column(0).combine_chunks()
                return (start, start + rows), values
            start += rows
        raise damaged(location.url, segment.samples, f"fewer rows than {MANIFEST_FILE} says ({segment.num_samples})")
    return None


def read_samples_row(location: Location, manifest: Manifest, position: int) -> dict[str, Any] | None:
    """Index row ``position`` of the manifest (its row group alone); None past the manifest's rows."""
    for segment in manifest.segments:
        if position >= segment.num_samples:
            position -= segment.num_samples
            continue
        file = samples_file(location, segment)
        for group in range(file.num_row_groups):
            rows = file.metadata.row_group(group).num_rows
            if position < rows:
                table = file.read_row_group(group, use_threads=False)
                return dict(table.slice(position, 1).to_pylist()[0])
            position -= rows
        raise damaged(location.url, segment.samples, f"fewer rows than {MANIFEST_FILE} says ({segment.num_samples})")
    return None


def read_task_samples(
    location: Location, manifest: Manifest, tasks: pa.Table, task_ids: Collection[str], columns: list[str]
) -> pa.Table:
    """``columns`` of the samples of ``task_ids`` (named by ``tasks``, the manifest's tasks table), in
    sample order, reading only the row groups that hold them: a part of a large dataset's index (what
    one worker of a parallel validation checks) without the rest."""
    counts = numpy_counts(tasks)
    ends = np.cumsum(counts)
    wanted = np.isin(np.asarray(tasks.column("task_id").to_pylist(), dtype=object), list(task_ids))
    starts = ends - counts
    keep = np.zeros(int(ends[-1]) if ends.size else 0, dtype=bool)
    for start, end in zip(starts[wanted].tolist(), ends[wanted].tolist(), strict=True):
        keep[start:end] = True
    pieces: list[pa.Table] = []
    offset = 0
    for segment in manifest.segments:
        file = samples_file(location, segment)
        group_start = offset
        for group in range(file.metadata.num_row_groups):
            rows = file.metadata.row_group(group).num_rows
            if keep[group_start : group_start + rows].any():
                table = file.read_row_group(group, columns=columns, use_threads=False)
                pieces.append(table.filter(pa.array(keep[group_start : group_start + rows])))
            group_start += rows
        offset += segment.num_samples
    if not pieces:
        schema = INDEX_SCHEMAS[manifest.schema_version]
        return pa.schema([schema.field(name) for name in columns]).empty_table()
    return pa.concat_tables(pieces)


def numpy_counts(tasks: pa.Table) -> npt.NDArray[np.int64]:
    """Samples per task of a tasks table."""
    return np.asarray(tasks.column("num_samples").to_pylist(), dtype=np.int64)


def count_values(location: Location, manifest: Manifest, name: str) -> dict[Any, int]:
    """How many samples hold each value of column ``name``, read a row group at a time (a string
    column as its dictionary): memory holds one row group, not a column of millions."""
    counts: dict[Any, int] = {}
    for segment in manifest.segments:
        file = samples_file(location, segment)
        for group in range(file.num_row_groups):
            column = file.read_row_group(group, columns=[name], use_threads=False).column(0)
            counted = pc.value_counts(column)
            for value, count in zip(
                counted.field("values").to_pylist(), counted.field("counts").to_pylist(), strict=True
            ):
                counts[value] = counts.get(value, 0) + int(count)
    return counts


def read_samples(location: Location, manifest: Manifest) -> pa.Table:
    """Every index row of the manifest (all columns: a large dataset's whole index in memory)."""
    schema = INDEX_SCHEMAS[manifest.schema_version]
    tables = []
    for segment in manifest.segments:
        try:
            table = samples_file(location, segment).read(use_threads=False)
        except (pa.ArrowException, ValueError, OSError) as exc:
            raise damaged(location.url, segment.samples, f"unreadable Parquet ({first_line(exc)})") from None
        if index_schema_version(table.schema, manifest.schema_version) is None:
            raise damaged(location.url, segment.samples, "index columns match no known schema version")
        tables.append(table.cast(schema))
    return pa.concat_tables(tables).combine_chunks() if tables else schema.empty_table()


@dataclass(frozen=True)
class TaskRecords:
    """What a checker walks: every task's commit record (a packed dataset's from its manifest), the
    records that could not be read, and where a packed task's shard lies (shard -> pack, offset, size)."""

    records: list[CommitRecord]
    problems: list[Problem]
    spans: dict[str, tuple[str, int, int]]


def task_records(location: Location) -> TaskRecords:
    """Every task's record, sorted by task id: the commit records, or a packed dataset's manifest rows."""
    try:
        manifest = read_manifest(location)
    except DamagedFile:
        manifest = None  # `storage.validate` names it; the commit records are still read
    if manifest is None or not manifest.packed:
        records, problems = read_commits(location)
        return TaskRecords(records, problems, {})
    try:
        rows = read_tasks(location, manifest).to_pylist()
    except DamagedFile as exc:
        return TaskRecords([], [Problem("index", exc.relative, exc.problem, Mend.NONE)], {})
    records = sorted((record_of(row) for row in rows), key=lambda r: r.task_id)
    spans = {row["shard"]: (row["pack"], int(row["pack_offset"]), int(row["pack_size"])) for row in rows}
    return TaskRecords(records, [], spans)


def mark_adding(location: Location) -> None:
    """Say that a job is about to commit tasks to this dataset (`ADDING_FILE`), when it has a manifest
    they will be missing from until it is finalised again."""
    if location.exists(MANIFEST_FILE):
        location.write_atomic(ADDING_FILE, json.dumps({"since": time.time()}).encode())


def being_added_to(location: Location) -> bool:
    """Whether a job may have committed tasks since the manifest was written (`ADDING_FILE`)."""
    return location.exists(ADDING_FILE)


def listed_commits(location: Location) -> list[str]:
    """Task ids of the commit records, from one listing of ``commits/`` (sorted)."""
    return [name.removesuffix(".json") for name in location.listdir(COMMITS) if name.endswith(".json")]


# ---------------------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Finalised:
    """What `finalise` left: the manifest and how many tasks and samples it names."""

    manifest: Manifest
    num_tasks: int
    num_samples: int
    added_tasks: int
    """Tasks this call added (the rest were in the manifest already)."""


def finalise(location: Location, schema_version: int, commits: Sequence[CommitRecord] | None = None) -> Finalised:
    """Bring the manifest up to date with the commit records: a new segment holding the tasks committed
    since it was last written (all of them the first time), merged with the others past `MAX_SEGMENTS`.

    ``commits``: every commit record, when the caller read them already. A manifest naming a task that
    has no commit record any more (withdrawn by `datagen shards repair`, or lost), or one that cannot
    be read, is written again from the records alone.
    """
    listed = [r.task_id for r in commits] if commits is not None else listed_commits(location)
    try:
        manifest = read_manifest(location)
        known = set() if manifest is None else set(read_tasks(location, manifest).column("task_id").to_pylist())
    except DamagedFile:  # a damaged manifest is written again from the records
        manifest, known = None, set()
    if manifest is not None and manifest.packed:
        raise damaged(location.url, MANIFEST_FILE, "a packed dataset is read-only; it has no commit records")
    if manifest is not None and not known <= set(listed):
        manifest, known = None, set()  # a task withdrawn or lost: every segment is written again
    new = sorted(set(listed) - known)
    given = {r.task_id: r for r in commits} if commits is not None else {}
    segments = list(manifest.segments) if manifest is not None else []
    if new or not segments:
        segments.append(write_segment(location, schema_version, _committed(location, new, given)))
    if len(segments) > MAX_SEGMENTS:
        segments = [merge_segments(location, schema_version, segments)]
    result = Manifest(schema_version=schema_version, segments=segments)
    location.write_atomic(MANIFEST_FILE, result.model_dump_json(indent=1).encode())
    location.remove(ADDING_FILE)  # every commit listed above is named now
    _remove_unnamed(location, result)
    return Finalised(result, result.num_tasks, result.num_samples, len(new))


def _committed(
    location: Location, task_ids: list[str], given: dict[str, CommitRecord]
) -> Iterator[tuple[CommitRecord, pa.Table]]:
    """Each task's commit record and index fragment, in ``task_ids`` order, read side by side."""

    def read(task_id: str) -> tuple[CommitRecord, pa.Table]:
        record = given.get(task_id) or parse_record(location, commit_path(task_id), CommitRecord)
        table = read_index_table(location, record.index_fragment)
        if table.num_rows != record.num_samples:
            problem = f"{table.num_rows} rows, its commit record {commit_path(task_id)} says {record.num_samples}"
            raise damaged(location.url, record.index_fragment, problem, rerun_task=True)
        return record, table

    with ThreadPoolExecutor(max_workers=READ_THREADS) as pool:
        for start in range(0, len(task_ids), ROW_GROUP_TASKS):
            yield from pool.map(read, task_ids[start : start + ROW_GROUP_TASKS])


def write_segment(
    location: Location, schema_version: int, tasks: Iterable[tuple[CommitRecord, pa.Table]], **pack: Any
) -> Segment:
    """A new segment of ``tasks`` (commit record, index rows), written row group by row group: memory
    holds `ROW_GROUP_TASKS` tasks' rows at a time, whatever their number. ``pack``: per-task columns of
    a packed dataset (`storage.dataset.pack`), keyed by task id."""
    name = uuid.uuid4().hex[:12]
    segment = Segment(
        tasks=f"{INDEX_FOLDER}/tasks-{name}.parquet",
        samples=f"{INDEX_FOLDER}/samples-{name}.parquet",
        num_tasks=0,
        num_samples=0,
    )
    schema = INDEX_SCHEMAS[schema_version]
    task_rows: list[dict[str, Any]] = []
    batch: list[pa.Table] = []
    sink = _Sink(location, segment.samples)
    with sink, pq.ParquetWriter(sink.stream, schema, compression="zstd") as writer:
        for record, rows in tasks:
            extra = {k: v.get(record.task_id) for k, v in pack.items()}
            task_rows.append(task_row(record, **extra, **object_of(rows)))
            if not rows.schema.equals(schema, check_metadata=False):
                if index_schema_version(rows.schema, schema_version) != schema_version:
                    problem = f"index columns of another version than the dataset's {schema_version}"
                    raise damaged(location.url, record.index_fragment, problem, rerun_task=True)
                rows = rows.cast(schema)
            batch.append(rows)
            if len(batch) == ROW_GROUP_TASKS:
                writer.write_table(pa.concat_tables(batch))
                batch = []
        if batch:
            writer.write_table(pa.concat_tables(batch))
    sink.publish()
    table = pa.Table.from_pylist(task_rows, schema=TASKS_SCHEMA)
    _write_table(location, segment.tasks, table)
    total = int(pc.sum(table.column("num_samples")).as_py() or 0)
    return segment.model_copy(update={"num_tasks": table.num_rows, "num_samples": total})


def task_row(record: CommitRecord, **extra: Any) -> dict[str, Any]:
    """A commit record as one row of `TASKS_SCHEMA`."""
    row: dict[str, Any] = {
        "task_id": record.task_id,
        "attempt_id": record.attempt_id,
        "shard": record.shard,
        "index_fragment": record.index_fragment,
        "num_samples": record.num_samples,
        "schema_version": record.schema_version,
        "timings": record.timings.model_dump_json() if record.timings is not None else None,
        "stored_bytes": record.stored_bytes,
        "pack": None,
        "pack_offset": None,
        "pack_size": None,
        "object_id": None,
        "object_name": None,
        "rotation": None,
    }
    row.update(extra)
    return row


def object_of(rows: pa.Table) -> dict[str, Any]:
    """The object columns of a task's row in the tasks table, from its first index row (nulls without
    rows)."""
    if not rows.num_rows:
        return {"object_id": None, "object_name": None, "rotation": None}
    first = rows.slice(0, 1).select(["object_id", "object_name", "rotation"]).to_pylist()[0]
    return dict(first)


def record_of(row: dict[str, Any]) -> CommitRecord:
    """The commit record a tasks-table row was made from."""
    timings = row.get("timings")
    return CommitRecord(
        schema_version=int(row["schema_version"]),
        task_id=row["task_id"],
        attempt_id=row["attempt_id"],
        shard=row["shard"],
        index_fragment=row["index_fragment"],
        num_samples=int(row["num_samples"]),
        timings=TaskTimings.model_validate_json(timings) if timings else None,
        stored_bytes=row.get("stored_bytes"),
    )


def merge_segments(
    location: Location, schema_version: int, segments: Sequence[Segment], drop: Collection[str] = ()
) -> Segment:
    """One segment holding ``segments``' tasks and samples in their order, copied row group by row group,
    leaving out the tasks ``drop`` names."""
    name = uuid.uuid4().hex[:12]
    tasks = pa.concat_tables([read_parquet(location, s.tasks).cast(TASKS_SCHEMA) for s in segments])
    dropped = pa.array(sorted(drop), pa.string())
    if drop:
        tasks = tasks.filter(pc.invert(pc.is_in(tasks.column("task_id"), dropped)))
    merged = Segment(
        tasks=f"{INDEX_FOLDER}/tasks-{name}.parquet",
        samples=f"{INDEX_FOLDER}/samples-{name}.parquet",
        num_tasks=tasks.num_rows,
        num_samples=int(pc.sum(tasks.column("num_samples")).as_py() or 0),
    )
    schema = INDEX_SCHEMAS[schema_version]
    sink = _Sink(location, merged.samples)
    with sink, pq.ParquetWriter(sink.stream, schema, compression="zstd") as writer:
        for segment in segments:
            file = samples_file(location, segment)
            for group in range(file.num_row_groups):
                rows = file.read_row_group(group, use_threads=False).cast(schema)
                if drop:
                    rows = rows.filter(pc.invert(pc.is_in(rows.column("task_id"), dropped)))
                writer.write_table(rows)
    sink.publish()
    _write_table(location, merged.tasks, tasks)
    return merged


def withdraw_tasks(location: Location, task_ids: Collection[str]) -> None:
    """Take these tasks out of the manifest (their samples out of its tables), before their commit
    records go (`storage.checks.withdraw`): a reader never meets a manifest naming a task without one."""
    manifest = read_manifest(location)
    if manifest is None:
        return
    named = set(read_tasks(location, manifest).column("task_id").to_pylist())
    if not named & set(task_ids):
        return
    segment = merge_segments(location, manifest.schema_version, manifest.segments, drop=set(task_ids))
    result = manifest.model_copy(update={"segments": [segment]})
    location.write_atomic(MANIFEST_FILE, result.model_dump_json(indent=1).encode())


class _Sink:
    """Where a large table is written: straight into a temporary file beside its place on local disk
    (renamed into place by `publish`), into memory for an object store (one put)."""

    def __init__(self, location: Location, relative: str) -> None:
        self.location, self.relative = location, relative
        if location.is_local:
            target = location.path(relative)
            location.fs.makedirs(target.rsplit("/", 1)[0], exist_ok=True)
            self._temporary = f"{target}.tmp-{uuid.uuid4().hex}"
            self.stream: Any = pa.OSFile(self._temporary, "wb")
        else:
            self.stream = pa.BufferOutputStream()

    def __enter__(self) -> _Sink:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        """A write that failed leaves no temporary file behind."""
        if kind is not None and self.location.is_local:
            self.stream.close()
            with contextlib.suppress(OSError):
                os.unlink(self._temporary)

    def publish(self) -> None:
        if self.location.is_local:
            self.stream.close()
            os.replace(self._temporary, self.location.path(self.relative))
        else:
            self.location.write_atomic(self.relative, self.stream.getvalue().to_pybytes())


def _write_table(location: Location, relative: str, table: pa.Table) -> None:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    location.write_atomic(relative, sink.getvalue().to_pybytes())


def _remove_unnamed(location: Location, manifest: Manifest) -> None:
    """Segment files no manifest names any more (merged, or written again) once older than
    `UNNAMED_AGE` (a younger one may be another driver's, finalising the same job this moment), and the
    index files of earlier versions of this code (``index.parquet``, ``index.json``): readers use the
    manifest."""
    named = {path.rsplit("/", 1)[1] for s in manifest.segments for path in (s.tasks, s.samples)}
    now = time.time()
    for path, info in sorted(location.fs.find(location.path(INDEX_FOLDER), detail=True).items()):
        name = str(path).rsplit("/", 1)[-1]
        if name in named or not name.endswith(".parquet") or now - _modified(info) < UNNAMED_AGE:
            continue
        location.remove(f"{INDEX_FOLDER}/{name}")
    for legacy in ("index.json", "index.parquet"):
        location.remove(legacy)


def _modified(info: dict[str, Any]) -> float:
    """A listed file's modification time in seconds since the epoch (local ``mtime``; S3 ``LastModified``)."""
    found = info.get("mtime", info.get("LastModified", info.get("last_modified")))
    if isinstance(found, datetime):
        return found.timestamp()
    return float(found) if found is not None else 0.0
