"""Data contracts of datagen, importable with numpy, pyarrow and pydantic only.

A training package depends on ``schemas`` and ``storage`` and never on the pipeline.
"""

from schemas.config import (
    BUILTIN_VIEW_SPACE,
    GENERATED_VIEW_SPACE,
    MAX_VIEWS,
    CameraConfig,
    GenerationConfig,
    ViewSpaceConfig,
    canonical_json,
)
from schemas.dataset import DATASET_FILE, DatasetInfo
from schemas.errors import DatagenError
from schemas.index import INDEX_SCHEMA, CommitRecord, FailureRecord
from schemas.jobs import JobSpec, ObjectRef, TaskSpec
from schemas.shard import ShardAttributes, array_names
from schemas.version import SCHEMA_VERSION

__all__ = [
    "BUILTIN_VIEW_SPACE",
    "DATASET_FILE",
    "GENERATED_VIEW_SPACE",
    "INDEX_SCHEMA",
    "MAX_VIEWS",
    "SCHEMA_VERSION",
    "CameraConfig",
    "CommitRecord",
    "DatagenError",
    "DatasetInfo",
    "FailureRecord",
    "GenerationConfig",
    "JobSpec",
    "ObjectRef",
    "ShardAttributes",
    "TaskSpec",
    "ViewSpaceConfig",
    "array_names",
    "canonical_json",
]
