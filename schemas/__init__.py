"""Data contracts of datagen, importable with numpy, pyarrow and pydantic only.

A training package depends on ``schemas`` and ``storage`` and never on the pipeline.
"""

from typing import TYPE_CHECKING

from schemas.lazy import lazy_names

if TYPE_CHECKING:
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

_HOMES = {
    "BUILTIN_VIEW_SPACE": "schemas.config",
    "GENERATED_VIEW_SPACE": "schemas.config",
    "MAX_VIEWS": "schemas.config",
    "CameraConfig": "schemas.config",
    "GenerationConfig": "schemas.config",
    "ViewSpaceConfig": "schemas.config",
    "canonical_json": "schemas.config",
    "DATASET_FILE": "schemas.dataset",
    "DatasetInfo": "schemas.dataset",
    "DatagenError": "schemas.errors",
    "INDEX_SCHEMA": "schemas.index",
    "CommitRecord": "schemas.index",
    "FailureRecord": "schemas.index",
    "JobSpec": "schemas.jobs",
    "ObjectRef": "schemas.jobs",
    "TaskSpec": "schemas.jobs",
    "ShardAttributes": "schemas.shard",
    "array_names": "schemas.shard",
    "SCHEMA_VERSION": "schemas.version",
}
"""Where each public name is defined: imported from there when first used (`schemas.lazy`)."""
__getattr__, __dir__ = lazy_names(__name__, _HOMES)
