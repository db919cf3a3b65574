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
from schemas.version import SCHEMA_VERSION

__all__ = [
    "BUILTIN_VIEW_SPACE",
    "GENERATED_VIEW_SPACE",
    "MAX_VIEWS",
    "SCHEMA_VERSION",
    "CameraConfig",
    "GenerationConfig",
    "ViewSpaceConfig",
    "canonical_json",
]
