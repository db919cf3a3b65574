"""Plan a job: resolve an objects file into tasks (object x rotation), keeping line errors."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec
from schemas.config import GenerationConfig
from schemas.jobs import JobSpec, ObjectRef, TaskSpec


class PlannedTasks(Sequence[TaskSpec]):
    """A job's tasks in order (objects in file order, rotations ascending), each made when asked for:
    a plan of 400,000 tasks holds its 50,000 objects, not 400,000 specs."""

    def __init__(self, objects: Sequence[ObjectSpec], rotations: int) -> None:
        self._objects = list(objects)
        self._refs = [object_ref(spec) for spec in objects]
        self._rotations = rotations

    def __len__(self) -> int:
        return len(self._refs) * self._rotations

    @overload
    def __getitem__(self, index: int) -> TaskSpec: ...

    @overload
    def __getitem__(self, index: slice) -> list[TaskSpec]: ...

    def __getitem__(self, index: int | slice) -> TaskSpec | list[TaskSpec]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if not -len(self) <= index < len(self):
            raise IndexError(index)
        number, rotation = divmod(index % len(self), self._rotations)
        return TaskSpec(task_id=self._task_id(number, rotation), object=self._refs[number], rotation=rotation)

    def rows(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """(task id, the spec as JSON data) of every task in order, what the ledger stores, without a
        `TaskSpec` each: the same data as ``TaskSpec.model_dump(mode="json")``."""
        for number, ref in enumerate(self._refs):
            data = ref.model_dump(mode="json")
            for rotation in range(self._rotations):
                task_id = self._task_id(number, rotation)
                yield task_id, {"task_id": task_id, "object": data, "rotation": rotation}

    def _task_id(self, number: int, rotation: int) -> str:
        return self._objects[number].task_id(rotation)


@dataclass(frozen=True)
class JobPlan:
    """A planned job: its spec and its tasks, which the ledger stores as one row each."""

    spec: JobSpec
    tasks: PlannedTasks


def plan_job(objects_file: str | Path, config: GenerationConfig, out: str, job_id: str | None = None) -> JobPlan:
    """The job's tasks in file order, rotations ascending; bad lines become ``line_errors``."""
    listing = read_objects_file(objects_file)
    job = JobSpec(
        job_id=job_id or new_job_id(config),
        objects_file=str(Path(objects_file).resolve()),
        out=out,
        config=config,
        line_errors=[str(error) for error in listing.errors],
    )
    return JobPlan(job, PlannedTasks(listing.objects, config.rotations))


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
