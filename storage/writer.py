"""The commit protocol: how a task's samples become visible, exactly once, whatever crashes.

1. The attempt writes its shard group ``shards/<task>/<attempt>.zarr`` (a path no other attempt
   shares), then its index fragment ``shards/<task>/<attempt>.parquet``.
2. It publishes ``commits/<task>.json`` naming itself, last, atomically and only if no commit record
   exists yet. Readers follow commit records only, so they never see a half-written shard, and a
   slow old attempt finishing late can never replace the committed one.

A crash before step 2 leaves unreferenced files that a re-run ignores (and `sweep_orphans`
removes); a crash after it leaves a complete, committed task.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import ValidationError

from schemas.dataset import DATASET_FILE
from schemas.index import INDEX_SCHEMA, CommitRecord, FailureRecord
from schemas.shard import ShardAttributes
from schemas.version import SCHEMA_VERSION
from storage.location import Location
from storage.shards import write_shard_group

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


def shard_path(task_id: str, attempt_id: str) -> str:
    return f"{SHARDS}/{task_id}/{attempt_id}.zarr"


def fragment_path(task_id: str, attempt_id: str) -> str:
    return f"{SHARDS}/{task_id}/{attempt_id}.parquet"


def commit_path(task_id: str) -> str:
    return f"{COMMITS}/{task_id}.json"


def failure_path(task_id: str) -> str:
    return f"{FAILURES}/{task_id}.json"


def read_commit(location: Location, task_id: str) -> CommitRecord | None:
    if not location.exists(commit_path(task_id)):
        return None
    return CommitRecord.model_validate_json(location.read_bytes(commit_path(task_id)))


def write_task(location: Location, payload: ShardPayload, attempt_id: str) -> CommitRecord:
    """Write and commit one task's shard; returns the commit readers follow (this attempt's, or
    an earlier attempt's if that one committed first)."""
    attributes = payload.attributes.model_copy(update={"attempt_id": attempt_id})
    task_id = attributes.task_id
    existing = read_commit(location, task_id)
    if existing is not None:
        return existing
    shard = shard_path(task_id, attempt_id)
    fragment = fragment_path(task_id, attempt_id)
    write_shard_group(location, shard, attributes, payload.arrays)
    location.write_atomic(fragment, _fragment_bytes(payload, shard, attempt_id))
    record = CommitRecord(
        schema_version=SCHEMA_VERSION,
        task_id=task_id,
        attempt_id=attempt_id,
        shard=shard,
        index_fragment=fragment,
        num_samples=attributes.num_samples,
    )
    if location.create_exclusive(commit_path(task_id), record.model_dump_json().encode()):
        location.remove(failure_path(task_id))
        return record
    committed = read_commit(location, task_id)
    assert committed is not None
    return committed


def write_failure(location: Location, record: FailureRecord) -> None:
    """Record why a task has no shard (replaced by a later success)."""
    location.write_atomic(failure_path(record.task_id), record.model_dump_json().encode())


def read_failures(location: Location) -> list[FailureRecord]:
    records = []
    for name in location.listdir(FAILURES):
        if name.endswith(".json"):
            records.append(FailureRecord.model_validate_json(location.read_bytes(f"{FAILURES}/{name}")))
    return records


def committed_tasks(location: Location) -> list[CommitRecord]:
    """Every commit record, sorted by task id."""
    records = []
    for name in location.listdir(COMMITS):
        if name.endswith(".json"):
            records.append(CommitRecord.model_validate_json(location.read_bytes(f"{COMMITS}/{name}")))
    return sorted(records, key=lambda r: r.task_id)


def read_commits(location: Location) -> tuple[list[CommitRecord], list[str]]:
    """Commit records that parse, sorted by task id, and one problem line for each that does not
    (so a reader can name the damaged record instead of failing on it)."""
    records, problems = [], []
    for name in location.listdir(COMMITS):
        if not name.endswith(".json"):
            continue
        try:
            records.append(CommitRecord.model_validate_json(location.read_bytes(f"{COMMITS}/{name}")))
        except (ValidationError, OSError) as exc:
            problems.append(f"{COMMITS}/{name}: unparsable commit record ({type(exc).__name__}); re-run the task")
    return sorted(records, key=lambda r: r.task_id), problems


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


def sweep_orphans(location: Location) -> list[str]:
    """Delete attempt files no commit record names; returns what was removed (sorted)."""
    committed = {r.task_id: r for r in committed_tasks(location)}
    removed = []
    for task_id in location.listdir(SHARDS):
        record = committed.get(task_id)
        for name in location.listdir(f"{SHARDS}/{task_id}"):
            relative = f"{SHARDS}/{task_id}/{name}"
            if record is not None and relative in (record.shard, record.index_fragment):
                continue
            if record is None:
                continue  # an attempt may still be running; only committed tasks are swept
            location.remove(relative, recursive=True)
            removed.append(relative)
    return sorted(removed)


def _fragment_bytes(payload: ShardPayload, shard: str, attempt_id: str) -> bytes:
    count = payload.attributes.num_samples
    columns = dict(payload.index_rows)
    columns["shard"] = [shard] * count
    columns["row"] = list(range(count))
    columns["attempt_id"] = [attempt_id] * count
    table = pa.Table.from_pydict({f.name: columns[f.name] for f in INDEX_SCHEMA}, schema=INDEX_SCHEMA)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return bytes(sink.getvalue().to_pybytes())


def encode_json(data: dict[str, Any]) -> bytes:
    return json.dumps(data, sort_keys=True, indent=1, default=_json_default).encode()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON-serialisable: {type(value).__name__}")
