"""Job and task specs: what the ledger stores and the engine ships to workers (pydantic, JSON)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

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
    """A dataset job: a config, an output URL, its objects file and the lines of it that failed to resolve.

    Its tasks are not part of it: the ledger keeps each `TaskSpec` as a row of its own, so a job of
    100,000 tasks is not one document that every look at the job parses."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    job_id: str
    objects_file: str
    out: str
    config: GenerationConfig
    line_errors: list[str] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _without_tasks(cls, value: Any) -> Any:
        """A job ledgered before its tasks were rows of their own kept a copy of them here; the rows
        (the same specs) are the ones read."""
        if isinstance(value, dict) and "tasks" in value:
            return {key: item for key, item in value.items() if key != "tasks"}
        return value

    @field_validator("config", mode="before")
    @classmethod
    def _as_recorded(cls, value: Any) -> Any:
        """A job ledgered before a config field existed resumes with the value that reproduces it."""
        return stored_config(value)
