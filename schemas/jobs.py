"""Job and task specs: what the ledger stores and the engine ships to workers (pydantic, JSON)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from schemas.config import GenerationConfig, stored_config


class ObjectRef(BaseModel):
    """One object of a job: its source, options and identity (as resolved from an objects file)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: str
    """Absolute mesh path or URL, or ``builtin:NAME``."""
    name: str
    units: Literal["auto", "m", "mm"] = "auto"
    up: Literal["z", "y"] = "z"
    size: float | None = None
    variant: int | None = Field(default=None, ge=0)
    """Seed of a deformed variant of the object (``variant=`` in an objects file); None: as it is."""
    object_id: str
    origin: str = ""
    """``FILE:LINE`` where it was listed."""


class TaskSpec(BaseModel):
    """The unit of work, retry and output: one (object, rotation)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task_id: str
    object: ObjectRef
    rotation: int = Field(ge=0)


class JobSpec(BaseModel):
    """A dataset job: a config, an output URL and its tasks (plus object lines that failed to resolve)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    job_id: str
    objects_file: str
    out: str
    config: GenerationConfig
    tasks: list[TaskSpec]
    line_errors: list[str] = Field(default_factory=list)

    @field_validator("config", mode="before")
    @classmethod
    def _as_recorded(cls, value: Any) -> Any:
        """A job ledgered before a config field existed resumes with the value that reproduces it."""
        return stored_config(value)
