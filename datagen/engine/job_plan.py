"""Plan a job: resolve an objects file into tasks (object x rotation), keeping line errors."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec
from schemas.config import GenerationConfig
from schemas.jobs import JobSpec, ObjectRef, TaskSpec


@dataclass(frozen=True)
class JobPlan:
    """A planned job: its spec and its tasks, which the ledger stores as one row each."""

    spec: JobSpec
    tasks: list[TaskSpec]


def plan_job(objects_file: str | Path, config: GenerationConfig, out: str, job_id: str | None = None) -> JobPlan:
    """The job's tasks in file order, rotations ascending; bad lines become ``line_errors``."""
    listing = read_objects_file(objects_file)
    tasks: list[TaskSpec] = []
    for spec in listing.objects:
        ref = object_ref(spec)  # one per object, shared by its rotations' tasks
        tasks.extend(TaskSpec(task_id=spec.task_id(r), object=ref, rotation=r) for r in range(config.rotations))
    job = JobSpec(
        job_id=job_id or new_job_id(config),
        objects_file=str(Path(objects_file).resolve()),
        out=out,
        config=config,
        line_errors=[str(error) for error in listing.errors],
    )
    return JobPlan(job, tasks)


def new_job_id(config: GenerationConfig) -> str:
    """Time-ordered and short: ``YYYYmmdd-HHMMSS-<6 hex of the config hash and time>``."""
    now = time.time()
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(now))
    salt = hashlib.sha256(f"{config.config_hash()}{now}".encode()).hexdigest()[:6]
    return f"{stamp}-{salt}"


def object_ref(spec: ObjectSpec) -> ObjectRef:
    return ObjectRef(
        source=spec.source,
        name=spec.name,
        units=spec.options.units,
        up=spec.options.up,
        size=spec.options.size,
        variant=spec.options.variant,
        object_id=spec.object_id,
        origin=spec.origin,
    )


def object_spec(ref: ObjectRef, generator: dict[str, object] | None = None) -> ObjectSpec:
    return ObjectSpec(
        source=ref.source,
        name=ref.name,
        options=ObjectOptions(units=ref.units, up=ref.up, size=ref.size, variant=ref.variant),
        object_id=ref.object_id,
        origin=ref.origin,
        generator=dict(generator or {}),
    )
