"""What one worker does for one task: prepare, compute, write the shard, report. Ray-free.

The engine calls `execute_task` inside a Ray task; tests call it directly. Bad input (a missing or
corrupt mesh) is an outcome, not an exception: the failure is recorded in the dataset and reported
so the job goes on. A task already committed (by an earlier attempt or another driver) is not
recomputed. A store that fails under a task (an S3 server restarting: connection refused, 5xx) is
waited for: its reads and its shard write are tried again, `STORE_RETRY_WAITS` apart, before the
task fails.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from datagen.engine.job_plan import object_spec
from datagen.engine.shard_payload import task_payload
from datagen.errors import ConfigError, DatagenError
from datagen.pipeline.objects.prepare import PreparedObject, prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.step_timing import StepClock
from datagen.pipeline.task import run_task
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas
from datagen.pipeline.viewspace import ViewSpace, build_view_space
from schemas.config import GenerationConfig
from schemas.index import failure_record
from schemas.jobs import ObjectRef, TaskSpec
from schemas.version import SCHEMA_VERSION
from storage import is_s3, is_transient, open_location, read_commit, write_failure, write_task

if TYPE_CHECKING:
    from datagen.pipeline.refine.poco.network_jobs import NetworkRunner

T = TypeVar("T")

STORE_RETRY_WAITS = (2.0, 5.0, 10.0, 20.0, 30.0)
"""Seconds before each new try of a task's store reads and shard write when the store failed under
them (after the request-level retries of `RunSettings.storage_options`): a store down for about a
minute (a restarting S3 server) costs a wait, not a failed task. Partial files of a failed write
are never followed (the commit record is written last) and are swept when the job ends."""


@dataclass(frozen=True)
class TaskOutcome:
    task_id: str
    ok: bool
    samples: int
    attempt_id: str
    """The storage attempt readers follow (this execution's, or an earlier committed one)."""
    message: str = ""
    reused: bool = False
    """True when the task was already committed and nothing was computed."""
    seconds: float = 0.0
    warnings: tuple[str, ...] = ()
    """What the job's report should say of the task's object (a flat mesh), one line each."""


class TaskBody(Protocol):
    """What the engine runs for each claimed task inside a Ray task (`datagen.engine.driver.run_job`'s
    ``body``): `execute_task` makes and commits the task's samples; `empty_task` does nothing, so the
    driver, the ledger and Ray's scheduling can be measured and tested alone. A body is a module-level
    function (Ray ships it by reference, so every worker imports it); it reports bad input as an
    outcome and raises only for bugs or a failed store."""

    def __call__(
        self,
        spec: TaskSpec,
        config: GenerationConfig,
        out: str,
        attempt_id: str,
        storage_options: dict[str, Any] | None = None,
        device: str = "cpu",
        config_hash: str | None = None,
        schema_version: int = SCHEMA_VERSION,
        network: NetworkRunner | None = None,
    ) -> TaskOutcome: ...


def empty_task(
    spec: TaskSpec,
    config: GenerationConfig,
    out: str,
    attempt_id: str,
    storage_options: dict[str, Any] | None = None,
    device: str = "cpu",
    config_hash: str | None = None,
    schema_version: int = SCHEMA_VERSION,
    network: NetworkRunner | None = None,
) -> TaskOutcome:
    """A `TaskBody` that computes and writes nothing: done at once with ``rotation + 1`` samples (so sums
    over tasks are checkable). For measuring the engine's own cost per task (``benchmarks/scale``) and
    testing it at scale in seconds; its dataset holds no shards."""
    return TaskOutcome(spec.task_id, True, spec.rotation + 1, f"{attempt_id}-empty")


def execute_task(
    spec: TaskSpec,
    config: GenerationConfig,
    out: str,
    attempt_id: str,
    storage_options: dict[str, Any] | None = None,
    device: str = "cpu",
    config_hash: str | None = None,
    schema_version: int = SCHEMA_VERSION,
    network: NetworkRunner | None = None,
) -> TaskOutcome:
    """Run one task end to end and commit its shard under a unique execution id.

    ``device`` is where a learned refiner runs ('cuda' when the engine reserved a GPU share).
    ``config_hash`` is the dataset's: a worker whose files give another hash (other shipped weights
    on this node) fails the task rather than mix two refiners in one dataset. ``schema_version`` is
    the dataset's layout, which its shards keep (a resumed version-1 dataset stays version 1).
    ``network`` runs a learned refiner's network elsewhere (its node's shared host,
    `datagen.engine.refiner_host`); where its time went joins the task's steps.
    """
    started = time.perf_counter()
    clock = StepClock()
    frozen = config.model_dump_json()
    generation = _config(frozen)
    location = open_location(out, storage_options)
    remote = is_s3(out)  # a local disk that fails does not come back by waiting
    committed = _store_retried(lambda: read_commit(location, spec.task_id), remote)
    if committed is not None:
        return TaskOutcome(spec.task_id, True, committed.num_samples, committed.attempt_id, reused=True)
    execution = f"{attempt_id}-{uuid.uuid4().hex[:8]}"
    try:
        if config_hash is not None and generation.config_hash() != config_hash:
            files = ", ".join(f"{name} = {path}" for name, path in generation.named_files().items())
            raise ConfigError(
                f"this worker's files give config hash {generation.config_hash()[:12]}, the dataset's is "
                f"{config_hash[:12]} ({files}): install the same datagen and weights on every node"
            )
        refiner = make_refiner(generation, device, network)  # first: it may import torch, which the bound below fixes
        with single_threaded_blas(), fixed_torch_threads():
            with clock.step("prepare"):  # ~0 when this worker prepared the object for another rotation
                prepared = _prepared(spec.object.model_dump_json(), frozen)
            result = run_task(prepared, spec.rotation, generation, _view_space(frozen), refiner, clock=clock)
        for name, (cpu, wall) in ({} if network is None else network.steps()).items():
            clock.add(name, cpu, wall)
    except DatagenError as exc:
        failure = failure_record(spec.task_id, str(exc), object_name=spec.object.name, origin=spec.object.origin)
        write_failure(location, failure)
        return TaskOutcome(spec.task_id, False, 0, execution, message=str(exc), seconds=time.perf_counter() - started)
    with clock.step("write"):  # the writer adds its own part: the shard and the index fragment
        payload = task_payload(result, generation, schema_version)
    payload = dataclasses.replace(payload, timings=clock.timings())

    def write() -> Any:  # a new execution id per try: a failed try's partial files are orphans
        return write_task(location, payload, f"{attempt_id}-{uuid.uuid4().hex[:8]}")

    record = _store_retried(write, remote)
    warned = prepared.flat_warning()
    return TaskOutcome(
        spec.task_id,
        True,
        record.num_samples,
        record.attempt_id,
        seconds=time.perf_counter() - started,
        warnings=(warned,) if warned else (),
    )


def _store_retried(action: Callable[[], T], remote: bool = True) -> T:
    """``action()``, tried again after each of `STORE_RETRY_WAITS` while a remote store fails under it."""
    if not remote:
        return action()
    for wait in STORE_RETRY_WAITS:
        try:
            return action()
        except Exception as error:
            if not is_transient(error):
                raise
            # one line in the worker's log (Ray keeps it per worker process): the wait is visible
            first = (str(error).strip().splitlines() or [type(error).__name__])[0][:200]
            print(f"datagen: the store failed under a task ({first}); trying again in {wait:g} s", file=sys.stderr)
            time.sleep(wait)
    return action()


@functools.lru_cache(maxsize=4)
def _config(frozen: str) -> GenerationConfig:
    return GenerationConfig.model_validate_json(frozen)


@functools.lru_cache(maxsize=4)
def _view_space(frozen: str) -> ViewSpace:
    return build_view_space(_config(frozen).view_space)


@functools.lru_cache(maxsize=8)
def _prepared(object_json: str, frozen: str) -> PreparedObject:
    """Prepared objects are reused across the rotations a worker runs (same object, same config)."""
    return prepare_object(object_spec(ObjectRef.model_validate_json(object_json)), _config(frozen))
