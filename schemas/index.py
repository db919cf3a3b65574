"""The Parquet index (one row per sample) and the records that sit beside the shards.

The index lets a reader filter and split without opening any shard: every column of docs/pipeline.md
section 8's metadata, plus where the sample lives (shard path relative to the dataset root, row).
Masks are stored as uint64 bit masks (bit i = view i).
"""

from __future__ import annotations

import pyarrow as pa
from pydantic import BaseModel, ConfigDict

from schemas.version import SCHEMA_VERSION

INDEX_SCHEMA_V1 = pa.schema(
    [
        pa.field("sample_id", pa.string(), nullable=False),
        pa.field("task_id", pa.string(), nullable=False),
        pa.field("object_id", pa.string(), nullable=False),
        pa.field("object_name", pa.string(), nullable=False),
        pa.field("rotation", pa.int16(), nullable=False),
        pa.field("view_state", pa.uint64(), nullable=False),
        pa.field("label", pa.uint64(), nullable=False),
        pa.field("case_size", pa.int16(), nullable=False),
        pa.field("label_size", pa.int16(), nullable=False),
        pa.field("num_points", pa.int32(), nullable=False),
        pa.field("num_observed", pa.int32(), nullable=False),
        pa.field("full_size", pa.int32(), nullable=False),
        pa.field("universe_size", pa.int32(), nullable=False),
        pa.field("empty_label", pa.bool_(), nullable=False),
        pa.field("solver_status", pa.string(), nullable=False),
        pa.field("solver_objective", pa.int16(), nullable=False),
        pa.field("solver_proof", pa.string(), nullable=False),
        pa.field("solver_seconds", pa.float64(), nullable=False),
        pa.field("rows_before", pa.int32(), nullable=False),
        pa.field("rows_after", pa.int32(), nullable=False),
        pa.field("refiner", pa.string(), nullable=False),
        pa.field("weights_id", pa.string(), nullable=False),
        pa.field("device", pa.string(), nullable=False),
        pa.field("seed", pa.int64(), nullable=False),
        pa.field("config_hash", pa.string(), nullable=False),
        pa.field("schema_version", pa.int16(), nullable=False),
        pa.field("shard", pa.string(), nullable=False),
        pa.field("row", pa.int32(), nullable=False),
        pa.field("attempt_id", pa.string(), nullable=False),
    ]
)
"""One row per sample. ``shard`` is relative to the dataset root; ``row`` is the sample's row there.
Only ``solver_seconds``, ``attempt_id`` and ``shard`` may differ between two runs of one job."""

AMBIGUITY_FIELDS = (
    pa.field("label_support", pa.uint64(), nullable=False),
    pa.field("min_covers", pa.int64(), nullable=False),
    pa.field("min_covers_exact", pa.bool_(), nullable=False),
)
"""Version 2: the views of any minimum cover, how many minimum covers there are (a lower bound
unless ``min_covers_exact``)."""

NEXT_VIEW_FIELDS = (
    pa.field("visible_size", pa.int32(), nullable=False),
    pa.field("best_view", pa.int16(), nullable=False),
    pa.field("best_view_ties", pa.int16(), nullable=False),
    pa.field("best_gain", pa.int32(), nullable=False),
)
"""Version 3: the keys any view sees (the visibility gains' denominator), the best next view (the
largest visibility gain outside the case, lowest index among equals; -1 when the case has every view),
how many views share its gain, and that gain (0 without a next view)."""

INDEX_SCHEMAS: dict[int, pa.Schema] = {
    1: INDEX_SCHEMA_V1,
    2: pa.schema([*INDEX_SCHEMA_V1, *AMBIGUITY_FIELDS]),
    3: pa.schema([*INDEX_SCHEMA_V1, *AMBIGUITY_FIELDS, *NEXT_VIEW_FIELDS]),
    4: pa.schema([*INDEX_SCHEMA_V1, *AMBIGUITY_FIELDS, *NEXT_VIEW_FIELDS]),
    5: pa.schema([*INDEX_SCHEMA_V1, *AMBIGUITY_FIELDS, *NEXT_VIEW_FIELDS]),
}
INDEX_SCHEMA = INDEX_SCHEMAS[SCHEMA_VERSION]
"""The index as this version writes it."""


def index_schema_version(schema: pa.Schema, expected: int | None = None) -> int | None:
    """The layout version whose index columns ``schema`` has (names and types, in order; nullability
    is not compared): ``expected`` when it has them (versions 3 and 4 share their columns, 4 changed
    only the shards' point order), else the lowest that has them; None for none."""
    if expected in INDEX_SCHEMAS and schema.equals(INDEX_SCHEMAS[expected], check_metadata=False):
        return expected  # the common case, without listing every version's fields
    found = [(field.name, field.type) for field in schema]
    matching = [
        version
        for version, known in sorted(INDEX_SCHEMAS.items())
        if found == [(field.name, field.type) for field in known]
    ]
    if expected in matching:
        return expected
    return matching[0] if matching else None


VOLATILE_COLUMNS = ("solver_seconds", "attempt_id", "shard")

TASK_STEPS = (
    "prepare",
    "ground_truth",
    "imaging",
    "refine_views",
    "cases",
    "refine_cases",
    "coverage",
    "labels",
    "next_view",
    "write",
)
"""The timed steps of one task, in the order they run: preparing the object (0 when the worker had
it prepared for another rotation), P_gt, imaging the n views, refining each single view, drawing the
long-tail cases, refining each multi-view case, counting P_full's coverage, the exact labels, the
next-view labels (gains and the occupancy grid's ray walks), and building and writing the shard and
index fragment."""


class StepSeconds(BaseModel):
    """CPU-seconds (the worker process's: its helper threads, Embree's or torch's, included) and
    wall seconds of one step."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    cpu: float
    wall: float


class TaskTimings(BaseModel):
    """Where one task's time went (`TASK_STEPS`); volatile, so kept out of samples and hashes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    steps: dict[str, StepSeconds]
    total: StepSeconds
    """The whole task in the worker, from its start to its commit record: the steps and what lies
    between them (the committed check, loading the refiner, which a worker process does once)."""


class CommitRecord(BaseModel):
    """Written last and atomically: names the one attempt of a task that readers follow."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: int
    task_id: str
    attempt_id: str
    shard: str
    """Shard group path relative to the dataset root."""
    index_fragment: str
    """Index fragment path relative to the dataset root."""
    num_samples: int
    timings: TaskTimings | None = None
    """Per-step time of the attempt that committed; None in datasets written before it was kept (and
    in relabelled ones, whose tasks are not computed again)."""
    stored_bytes: int | None = None
    """Bytes of the shard and index fragment as written (a one-file shard's layout, version 5 on); None
    where a listing must tell (older records, the folder layout)."""


class FailureRecord(BaseModel):
    """Why a task (or an object line) produced no shard, kept in the dataset itself."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: int
    task_id: str
    object_name: str
    origin: str
    """Where the object was listed: ``FILE:LINE``."""
    message: str


def failure_record(task_id: str, message: str, *, object_name: str = "", origin: str = "") -> FailureRecord:
    """The `FailureRecord` this datagen writes: a task's (its object's name and ``FILE:LINE``) or an
    object line's that never became a task (no name)."""
    return FailureRecord(
        schema_version=SCHEMA_VERSION, task_id=task_id, object_name=object_name, origin=origin, message=message
    )
