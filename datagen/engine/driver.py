"""The engine: run a job's tasks on Ray, record every state change in the ledger.

The only module that imports Ray. The driver claims tasks from the ledger (leases it renews while
alive), keeps a bounded number in flight as Ray tasks, and records each outcome. Workers compute and
commit whole shards through `storage`; the driver never touches sample data. Ray retries tasks
whose worker process died; a dead driver's leases expire and `resume` (or another driver on the
same ledger) claims those tasks again, while committed tasks are never recomputed.
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import platform
import socket
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from datagen.engine.worker import TaskOutcome, execute_task
from datagen.errors import ConfigError
from datagen.pipeline.viewspace import build_view_space
from jobs.ledger import CANCELLED, DONE, FAILED, PENDING, RUNNING, Job, Ledger
from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.index import FailureRecord
from schemas.jobs import JobSpec, TaskSpec
from schemas.version import SCHEMA_VERSION
from storage import StorageError, finalise, init_dataset, open_location, storage_failure, write_failure

LEASE_SECONDS = 120.0
RENEW_EVERY = 20.0
TASK_RETRIES = 3
"""Ray re-executions of a task whose worker process died (system failures, not bad input)."""


@dataclass
class JobProgress:
    """What the driver reports while a job runs (for the progress display)."""

    total: int
    done: int = 0
    failed: int = 0
    samples: int = 0
    messages: list[str] = field(default_factory=list)


ProgressCallback = Callable[[JobProgress], None]


def ensure_ray(address: str | None, num_cpus: int | None) -> None:
    """Connect to a cluster (address or RAY_ADDRESS) or start a local Ray once per process."""
    import ray

    if ray.is_initialized():
        return
    env = {"env_vars": {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
    if address:
        ray.init(address=address, runtime_env=env, log_to_driver=False, logging_level=logging.ERROR)
    else:
        # "local": always a private Ray of our own, even when `ray start` left a cluster running on
        # this machine (joining it would need --address, and would ignore --workers).
        ray.init(
            address="local",
            num_cpus=num_cpus,
            include_dashboard=False,
            runtime_env=env,
            log_to_driver=False,
            logging_level=logging.ERROR,
        )


def _remote_execute(
    task: TaskSpec,
    config: GenerationConfig,
    out: str,
    attempt_id: str,
    storage_options: dict[str, Any] | None,
    device: str,
) -> tuple[TaskOutcome, str]:
    import ray

    outcome = execute_task(task, config, out, attempt_id, storage_options, device)
    context = ray.get_runtime_context()
    return outcome, f"{context.get_node_id()[:12]}@{socket.gethostname()}"


def dataset_info(config: GenerationConfig) -> DatasetInfo:
    view_space = build_view_space(config.view_space)
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    for package in ("datagen", "trimesh", "embreex", "highspy", "zarr", "pyarrow", "ray"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            continue
    return DatasetInfo(
        schema_version=SCHEMA_VERSION,
        config=config,
        config_hash=config.config_hash(),
        view_positions=[(float(x), float(y), float(z)) for x, y, z in view_space.positions.tolist()],
        versions=versions,
        created=datetime.now(UTC).isoformat(timespec="seconds"),
    )


def run_job(
    ledger: Ledger,
    job_id: str,
    address: str | None = None,
    num_cpus: int | None = None,
    storage_options: dict[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    max_in_flight: int | None = None,
    refiner_gpus: float = 0.0,
) -> Job:
    """Run every runnable task of a job to completion (or cancellation); returns the job.

    Each task reserves one CPU, and ``refiner_gpus`` of a GPU when that is > 0 (its learned refiner
    then runs on CUDA). Tasks are plain Ray tasks rather than a fixed pool of actors, so a node that
    joins or leaves mid-job simply gains or loses tasks; the refiner's weights are still loaded once
    per worker process, which Ray keeps between tasks.
    """
    import ray

    job = ledger.job(job_id)
    spec = JobSpec.model_validate(job.spec)
    config = spec.config
    tasks_by_id = {task.task_id: task for task in spec.tasks}
    location = open_location(job.out, storage_options)
    with _store_errors(job.out):
        init_dataset(location, dataset_info(config))
        for number, line_error in enumerate(spec.line_errors):
            origin, _, message = line_error.partition(": ")
            write_failure(
                location,
                FailureRecord(
                    schema_version=SCHEMA_VERSION,
                    task_id=f"line-{number:04d}",
                    object_name="",
                    origin=origin,
                    message=message,
                ),
            )
    ensure_ray(address, num_cpus)
    if refiner_gpus > 0 and not ray.cluster_resources().get("GPU", 0):
        raise ConfigError(
            f"refiner_gpus = {refiner_gpus:g} but the Ray cluster has no GPU; drop --refiner-gpus to refine on CPU"
        )
    owner = f"driver-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    ledger.start_job(job_id, owner)
    remote = ray.remote(num_cpus=1, num_gpus=refiner_gpus, max_retries=TASK_RETRIES, retry_exceptions=False)(
        _remote_execute
    )
    device = "cuda" if refiner_gpus > 0 else "cpu"
    capacity = max_in_flight or max(1, int(ray.cluster_resources().get("CPU", 1)))
    tasks = ledger.tasks(job_id)
    state = JobProgress(total=len(tasks))
    state.done = sum(1 for t in tasks if t.state == DONE)
    state.failed = sum(1 for t in tasks if t.state == FAILED)
    state.samples = sum(t.samples or 0 for t in tasks if t.state == DONE)
    in_flight: dict[Any, tuple[str, str]] = {}
    last_renew = time.monotonic()
    cancelled = False
    while True:
        if ledger.job(job_id).state == CANCELLED:
            cancelled = True
            for ref in in_flight:
                ray.cancel(ref, force=True)
            break
        free = capacity - len(in_flight)
        if free > 0:
            for claim in ledger.claim(job_id, owner, LEASE_SECONDS, free):
                task = tasks_by_id[claim.task.task_id]
                ref = remote.remote(task, config, job.out, claim.attempt_id, storage_options, device)
                in_flight[ref] = (claim.task.task_id, claim.attempt_id)
        if not in_flight:
            break
        ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=1.0)
        for ref in ready:
            task_id, attempt_id = in_flight.pop(ref)
            _record(ledger, job_id, task_id, attempt_id, ref, state)
        if progress:
            progress(state)
        if time.monotonic() - last_renew > RENEW_EVERY:
            ledger.renew(job_id, owner, LEASE_SECONDS)
            last_renew = time.monotonic()
    counts = ledger.task_counts(job_id)
    if not cancelled and not counts.get(PENDING) and not counts.get(RUNNING):
        with _store_errors(job.out):
            finalise(location)
        summary = {
            "tasks": len(tasks),
            "done": counts.get(DONE, 0),
            "failed": counts.get(FAILED, 0) + len(spec.line_errors),
            "samples": state.samples,
            "line_errors": spec.line_errors,
            "failures": [
                f"{tasks_by_id[t.task_id].object.origin}: {t.task_id}: {t.error}"
                for t in ledger.tasks(job_id)
                if t.state == FAILED
            ],
        }
        ledger.finish_job(job_id, summary, other_failures=len(spec.line_errors))
    if progress:
        progress(state)
    return ledger.job(job_id)


@contextmanager
def _store_errors(url: str) -> Iterator[None]:
    """The driver's own store operations: any failure of the store (refused credentials, an
    unreachable endpoint once its timeout and retries are spent) becomes one `StorageError` line."""
    try:
        yield
    except StorageError:
        raise
    except Exception as error:  # botocore, aiohttp and fsspec raise many unrelated types
        raise storage_failure(url, error) from None


def _record(ledger: Ledger, job_id: str, task_id: str, attempt_id: str, ref: Any, state: JobProgress) -> None:
    import ray

    try:
        outcome, placement = ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        ledger.release(job_id, task_id, attempt_id)
        return
    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError, ray.exceptions.RayTaskError) as exc:
        # Ray's retries are spent (or the task raised: a bug): record the task as failed with the
        # reason, so the job ends and says why.
        message = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        ledger.fail(job_id, task_id, attempt_id, f"worker error: {message}")
        state.failed += 1
        state.messages.append(f"{task_id}: {message}")
        return
    if outcome.ok:
        if ledger.complete(job_id, task_id, attempt_id, outcome.samples, placement):
            state.done += 1
            state.samples += outcome.samples
    else:
        if ledger.fail(job_id, task_id, attempt_id, outcome.message):
            state.failed += 1
            state.messages.append(f"{task_id}: {outcome.message}")
