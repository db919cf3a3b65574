"""The Parquet index (one row per sample) and the records that sit beside the shards.

The index lets a reader filter and split without opening any shard: every column of PIPELINE.md
section 8's metadata, plus where the sample lives (shard path relative to the dataset root, row).
Masks are stored as uint64 bit masks (bit i = view i).
"""

from __future__ import annotations

import pyarrow as pa
from pydantic import BaseModel, ConfigDict

INDEX_SCHEMA = pa.schema(
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

VOLATILE_COLUMNS = ("solver_seconds", "attempt_id", "shard")


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


class FailureRecord(BaseModel):
    """Why a task (or an object line) produced no shard, kept in the dataset itself."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: int
    task_id: str
    object_name: str
    origin: str
    """Where the object was listed: ``FILE:LINE``."""
    message: str
