"""The commit protocol: how a task's samples become visible, exactly once, whatever crashes.

1. The attempt writes its shard group ``shards/<task>/<attempt>.zarr.zip`` (one file from layout 5,
   a folder ``<attempt>.zarr`` before; a path no other attempt shares), then its index fragment
   ``shards/<task>/<attempt>.parquet``.
2. It publishes ``commits/<task>.json`` naming itself, last, atomically and only if no commit record
   exists yet. Readers follow commit records only, so they never see a half-written shard, and a
   slow old attempt finishing late can never replace the committed one.

A crash before step 2 leaves unreferenced files that a re-run ignores (and `sweep_orphans`
removes); a crash after it leaves a complete, committed task.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
import pyarrow as pa
from pydantic import ValidationError

from schemas.dataset import DATASET_FILE
from schemas.index import INDEX_SCHEMAS, CommitRecord, FailureRecord, StepSeconds, TaskTimings
from schemas.shard import ShardAttributes, shard_suffix
from schemas.version import SCHEMA_VERSION
from storage.dataset.problems import Mend, Problem
from storage.shards.groups import write_shard_group
from storage.store.location import RERUN_FIX, DamagedFile, Location, damaged, first_validation_error, is_temporary
from storage.store.parquet import parquet_bytes

COMMITS = "commits"
FAILURES = "failures"
SHARDS = "shards"


@dataclass(frozen=True)
class ShardPayload:
    """Everything one task writes: arrays (`schemas.shard` names), group attributes, index rows.

    ``index_rows`` hold every `INDEX_SCHEMA` column except ``shard``, ``row`` and ``attempt_id``,
    which the writer fills in; rows are in shard row order.
    """

    attributes: ShardAttributes
    arrays: dict[str, npt.NDArray[Any]]
    index_rows: dict[str, list[Any]]
    timings: TaskTimings | None = None
    """The task's per-step time so far; `write_task` adds its write and keeps it in the commit record."""


def shard_path(task_id: str, attempt_id: str, schema_version: int = SCHEMA_VERSION) -> str:
    return f"{SHARDS}/{task_id}/{attempt_id}{shard_suffix(schema_version)}"


def fragment_path(task_id: str, attempt_id: str) -> str:
    return f"{SHARDS}/{task_id}/{attempt_id}.parquet"


def commit_path(task_id: str) -> str:
    return f"{COMMITS}/{task_id}.json"


def failure_path(task_id: str) -> str:
    return f"{FAILURES}/{task_id}.json"


def read_commit(location: Location, task_id: str) -> CommitRecord | None:
    if not location.exists(commit_path(task_id)):
        return None
    return parse_record(location, commit_path(task_id), CommitRecord)


Record = TypeVar("Record", CommitRecord, FailureRecord)


def parse_record(location: Location, relative: str, model: type[Record]) -> Record:
    """A commit or failure record; `DamagedFile` naming it when it cannot be read or parsed."""
    try:
        return model.model_validate_json(location.read_bytes(relative))
    except FileNotFoundError:
        raise damaged(location.url, relative, "missing", rerun_task=True) from None
    except ValidationError as exc:
        kind = "commit" if model is CommitRecord else "failure"
        problem = f"unparsable {kind} record ({first_validation_error(exc)})"
        raise damaged(location.url, relative, problem, rerun_task=True) from None


def write_task(location: Location, payload: ShardPayload, attempt_id: str) -> CommitRecord:
    """Write and commit one task's shard; returns the commit readers follow (this attempt's, or
    an earlier attempt's if that one committed first)."""
    attributes = payload.attributes.model_copy(update={"attempt_id": attempt_id})
    task_id = attributes.task_id
    existing = read_commit(location, task_id)
    if existing is not None:
        return existing
    shard = shard_path(task_id, attempt_id, attributes.schema_version)
    fragment = fragment_path(task_id, attempt_id)
    cpu, wall = time.process_time(), time.perf_counter()
    shard_bytes = write_shard_group(location, shard, attributes, payload.arrays)
    fragment_bytes = _fragment_bytes(payload, shard, attempt_id)
    location.write_atomic(fragment, fragment_bytes)
    record = CommitRecord(
        schema_version=attributes.schema_version,
        task_id=task_id,
        attempt_id=attempt_id,
        shard=shard,
        index_fragment=fragment,
        num_samples=attributes.num_samples,
        timings=_with_write(payload.timings, time.process_time() - cpu, time.perf_counter() - wall),
        stored_bytes=None if shard_bytes is None else shard_bytes + len(fragment_bytes),
    )
    if location.create_exclusive(commit_path(task_id), record.model_dump_json().encode()):
        location.remove(failure_path(task_id))
        return record
    committed = read_commit(location, task_id)
    assert committed is not None
    return committed


def _with_write(timings: TaskTimings | None, cpu: float, wall: float) -> TaskTimings | None:
    """``timings`` with this write's seconds added to its ``write`` step and its total."""
    if timings is None:
        return None
    before = timings.steps.get("write", StepSeconds(cpu=0.0, wall=0.0))
    steps = {**timings.steps, "write": StepSeconds(cpu=before.cpu + cpu, wall=before.wall + wall)}
    total = StepSeconds(cpu=timings.total.cpu + cpu, wall=timings.total.wall + wall)
    return TaskTimings(steps=steps, total=total)


def write_failure(location: Location, record: FailureRecord) -> None:
    """Record why a task has no shard (removed by a later success).

    Not written when the task is committed already (another attempt won; readers follow the
    commit). A task may still hold both records, legitimately: a writer killed between its commit
    and removing the failure, or a failing attempt that checked just before another committed.
    The commit wins; `storage.validate` names the stale failure record as a warning.
    """
    if location.exists(commit_path(record.task_id)):
        return
    location.write_atomic(failure_path(record.task_id), record.model_dump_json().encode())


LINE_PREFIX = "line-"
"""Failure records of objects-file lines that never became a task: ``line-<16 hex of FILE:LINE>``."""


def line_failure_id(origin: str) -> str:
    """The record id of objects-file line ``origin`` (``FILE:LINE``): the same line keeps one record
    across jobs, two files never share one."""
    return LINE_PREFIX + hashlib.sha256(origin.encode()).hexdigest()[:16]


def retire_line_failures(location: Location, objects_file: str) -> int:
    """Remove the failure records of ``objects_file``'s lines (a job of that file is about to record its
    own: a line fixed since then is no longer missing); how many were removed."""
    target = Path(objects_file).resolve()
    retired = 0
    for record in read_failures(location):
        if not record.task_id.startswith(LINE_PREFIX) or record.object_name:
            continue
        source = record.origin.rpartition(":")[0]
        if source and Path(source).resolve() == target:
            location.remove(failure_path(record.task_id))
            retired += 1
    return retired


def read_failures(location: Location) -> list[FailureRecord]:
    """Every failure record; `DamagedFile` naming the first one that cannot be parsed."""
    return [parse_record(location, relative, FailureRecord) for relative in _record_files(location, FAILURES)]


def committed_tasks(location: Location) -> list[CommitRecord]:
    """Every commit record, sorted by task id; `DamagedFile` naming the first unparsable one."""
    records = [parse_record(location, relative, CommitRecord) for relative in _record_files(location, COMMITS)]
    return sorted(records, key=lambda r: r.task_id)


def _record_files(location: Location, folder: str) -> list[str]:
    """``<folder>/<task>.json`` paths (temporaries of an interrupted write end otherwise)."""
    return [f"{folder}/{name}" for name in location.listdir(folder) if name.endswith(".json")]


def read_commits(location: Location) -> tuple[list[CommitRecord], list[Problem]]:
    """Commit records that parse, sorted by task id, and a problem for each that does not (so
    `storage.validate` can name every damaged record instead of stopping at the first)."""
    records, problems = _read_all(location, COMMITS, CommitRecord)
    return sorted(records, key=lambda r: r.task_id), problems


def read_failure_records(location: Location) -> tuple[list[FailureRecord], list[Problem]]:
    """Failure records that parse and a problem for each that does not."""
    return _read_all(location, FAILURES, FailureRecord)


def _read_all(location: Location, folder: str, model: type[Record]) -> tuple[list[Record], list[Problem]]:
    """The records of ``folder`` that parse; a damaged one (``<folder>/<task>.json``) is mended by
    re-running its task."""
    records: list[Record] = []
    problems: list[Problem] = []
    for relative in _record_files(location, folder):
        try:
            records.append(parse_record(location, relative, model))
        except DamagedFile as exc:
            task = relative.rsplit("/", 1)[-1].removesuffix(".json")
            problems.append(Problem("record", relative, f"{exc.problem}; {RERUN_FIX}", Mend.TASK, task))
    return records, problems


def stored_bytes(location: Location, commits: list[CommitRecord]) -> dict[str, int]:
    """Bytes of each committed task's shard group and index fragment, from one listing of ``shards/``
    (one request on an object store rather than one per task)."""
    listing = location.fs.find(location.path(SHARDS), detail=True)
    root = location.root.strip("/")
    owner: dict[str, str] = {}
    for record in commits:
        owner[record.index_fragment] = record.task_id
        owner[record.shard] = record.task_id
    sizes: dict[str, int] = {}
    for path, info in listing.items():
        relative = str(path).strip("/").removeprefix(f"{root}/" if root else "")
        task_id = owner.get(relative) or owner.get(_shard_group_of(relative))
        if task_id is not None:
            sizes[task_id] = sizes.get(task_id, 0) + int(info.get("size") or 0)
    return sizes


def _shard_group_of(relative: str) -> str:
    """``shards/<task>/<attempt>.zarr`` for a file inside that group (or "" for other paths)."""
    parts = relative.split("/")
    return "/".join(parts[:3]) if len(parts) > 3 and parts[2].endswith(".zarr") else ""


def holds_dataset(location: Location) -> bool:
    """True when the location already holds a dataset (its description or any commit record)."""
    return location.exists(DATASET_FILE) or bool(location.listdir(COMMITS))


def sweep_orphans(
    location: Location, finished: Collection[str] | None = None, commits: Collection[CommitRecord] | None = None
) -> list[str]:
    """Delete attempt files no commit record names; returns what was removed (sorted).

    Without ``finished`` only committed tasks are swept: an attempt of an uncommitted task may still
    be running. ``finished`` names tasks no attempt writes to any more (a job that ended): only those
    are swept, the uncommitted ones (failed) included; other tasks may belong to another job.
    ``commits``: every commit record, when the caller holds them (a finalised manifest's), else read.
    The shard folders are listed once, not one listing per task.
    """
    committed = {r.task_id: r for r in (committed_tasks(location) if commits is None else commits)}
    wanted = None if finished is None else set(finished)
    removed = []
    for task_id, names in sorted(_attempt_files(location).items()):
        record = committed.get(task_id)
        if (record is None) if wanted is None else (task_id not in wanted):
            continue
        keep = {record.shard, record.index_fragment} if record is not None else set()
        for name in names:
            relative = f"{SHARDS}/{task_id}/{name}"
            if relative not in keep:
                location.remove(relative, recursive=True)
                removed.append(relative)
    return sorted(removed)


def _attempt_files(location: Location) -> dict[str, list[str]]:
    """{task id: the names directly in its shard folder (files, or a folder-layout group)}, sorted: on
    local disk one scan of each folder, on an object store one recursive listing of ``shards/``."""
    found: dict[str, set[str]] = {}
    if location.is_local:
        try:
            tasks = list(os.scandir(location.path(SHARDS)))
        except FileNotFoundError:
            return {}
        for task in tasks:
            if task.is_dir():
                found[task.name] = {entry.name for entry in os.scandir(task.path)}
    else:
        base = location.path(SHARDS).strip("/")
        try:
            listed = location.fs.find(location.path(SHARDS))
        except FileNotFoundError:
            listed = []
        for path in listed:
            parts = str(path).strip("/").removeprefix(base).strip("/").split("/")
            if len(parts) >= 2:
                found.setdefault(parts[0], set()).add(parts[1])
    return {task: sorted(names) for task, names in found.items() if names}


def sweep_temporaries(location: Location, older_than: float) -> list[str]:
    """Delete temporary files of writes that never published (a full disk, a killed writer) at the
    dataset's top, in ``commits/`` and ``failures/``, once older than ``older_than`` seconds (a
    younger one may belong to a write in progress). Local datasets only: an object store has no
    temporary files (each object appears whole). Returns what was removed (sorted)."""
    if not location.is_local:
        return []
    now = time.time()
    removed = []
    for folder in ("", COMMITS, FAILURES):
        for name in location.listdir(folder):
            relative = f"{folder}/{name}" if folder else name
            if is_temporary(name) and now - os.path.getmtime(location.path(relative)) > older_than:
                location.remove(relative)
                removed.append(relative)
    return sorted(removed)


def _fragment_bytes(payload: ShardPayload, shard: str, attempt_id: str) -> bytes:
    count = payload.attributes.num_samples
    columns = dict(payload.index_rows)
    columns["shard"] = [shard] * count
    columns["row"] = list(range(count))
    columns["attempt_id"] = [attempt_id] * count
    schema = INDEX_SCHEMAS[payload.attributes.schema_version]
    return parquet_bytes(pa.Table.from_pydict({f.name: columns[f.name] for f in schema}, schema=schema))


def encode_json(data: dict[str, Any]) -> bytes:
    return json.dumps(data, sort_keys=True, indent=1, default=_json_default).encode()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")
