"""`RunSettings`: where and how a job runs. Never hashed, never written into a dataset.

This is the only module that reads datagen's environment variables (besides the CLI's options);
`storage.store.location` reads the standard AWS ones (endpoint, region) where a store is opened.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from jobs.ledger import Ledger

LEDGER_FILE = "ledger.db"
"""The ledger's file name inside the home folder (``RunSettings.home``)."""


def _env_number(name: str, default: float) -> float:
    value = os.environ.get(name)
    return float(value) if value not in (None, "") else default


def default_home() -> Path:
    return Path(os.environ.get("DATAGEN_HOME", str(Path.home() / ".datagen"))).expanduser()


class RunSettings(BaseModel):
    """Placement and resources of a run; changing them never changes a sample."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    home: Path = Field(default_factory=default_home)
    out: str | None = None
    ray_address: str | None = Field(default_factory=lambda: os.environ.get("RAY_ADDRESS"))
    num_workers: int | None = Field(None, ge=1)
    refiner_gpus: float = Field(0.0, ge=0.0, le=1.0)
    """Share of a GPU each task reserves; > 0 runs the poco refiner on CUDA (CPU and GPU results can
    differ in borderline keys, so keep one device per dataset)."""
    shared_refiner: bool = False
    """One POCO network per node, shared by its tasks (on its GPU with ``refiner_gpus`` > 0), instead
    of one per worker process (`datagen.engine.refiner_host`); the same samples either way."""
    refiner_batch: int = Field(1, ge=1, le=256)
    """Network jobs per encoder call on a shared refiner. 1 gives the samples of a refiner in the task
    bit for bit; more is for a GPU (latents move by float rounding, ~1e-7)."""
    storage_timeout: float = Field(default_factory=lambda: _env_number("DATAGEN_STORAGE_TIMEOUT", 20.0), gt=0.0)
    """Seconds to connect to, or wait on, an object store per request (DATAGEN_STORAGE_TIMEOUT)."""
    storage_retries: int = Field(default_factory=lambda: int(_env_number("DATAGEN_STORAGE_RETRIES", 4)), ge=1, le=20)
    """Attempts per object-store request before it fails (DATAGEN_STORAGE_RETRIES)."""

    def storage_options(self, url: str) -> dict[str, Any]:
        """fsspec options for a dataset URL: request timeouts and retries for S3, so an unreachable
        store or refused credentials fail the job after a bounded time instead of hanging."""
        from storage import is_s3  # fsspec loads with it: not at every command's start

        if not is_s3(url):
            return {}
        return {
            "config_kwargs": {
                "connect_timeout": self.storage_timeout,
                "read_timeout": self.storage_timeout,
                "retries": {"max_attempts": self.storage_retries, "mode": "standard"},
            }
        }


def ledger_for(settings: RunSettings) -> Ledger:
    """The job ledger of a home folder (``HOME/ledger.db``), created when missing: what `status`,
    `cancel` and the drivers open, without loading the engine."""
    return Ledger(Path(settings.home) / LEDGER_FILE)
