"""`RunSettings`: where and how a job runs. Never hashed, never written into a dataset.

This is the only module that reads environment variables (besides the CLI's options).
"""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field


def default_home() -> Path:
    return Path(os.environ.get("DATAGEN_HOME", str(Path.home() / ".datagen"))).expanduser()


class RunSettings(BaseModel):
    """Placement and resources of a run; changing them never changes a sample."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    home: Path = Field(default_factory=default_home)
    out: str | None = None
    ray_address: str | None = Field(default_factory=lambda: os.environ.get("RAY_ADDRESS"))
    num_workers: int | None = Field(None, ge=1)
    blas_threads: int = Field(1, ge=1)
    """BLAS threads per worker: 1, since tall-skinny matmuls run up to 100x slower with 2 here."""
