"""The engine: run a job's tasks on Ray, record every state change in the ledger.

The only module that imports Ray. The driver claims tasks from the ledger (leases it renews while
alive), keeps a bounded number in flight as Ray tasks, and records each outcome. Workers compute and
commit whole shards through `storage`; the driver never touches sample data. Ray retries tasks
whose worker process died; a dead driver's leases expire and `resume` (or another driver on the
same ledger) claims those tasks again, while committed tasks are never recomputed.

Liveness: the driver records itself on the job in the ledger (host, PID, process start) and renews a
heartbeat with its leases; a driver on the same machine whose process is gone is known lost at once,
so `resume` or `serve` take its tasks without waiting for its leases (`jobs.ledger`).

Several drivers on one job cooperate: task claims are exclusive, so a `resume` started while the
first driver still runs (or two `serve` loops) share the remaining tasks. With ``wait_for_others``
(`submit` and `resume`), a driver that runs out of tasks to claim waits for the tasks the others
still hold (taking over any whose driver is lost), then finalises the dataset and reports the job's
true final state; its summary counts the samples of the whole dataset, whoever computed them. A
serve loop passes ``wait_for_others=False`` and looks again later (`datagen.engine.serve`).

A task the ledger marks failed because its worker died (Ray's retries spent) or raised gets a
failure record written by the driver, as bad input gets one from the worker, so the dataset alone
says what is missing and why. Once a job is complete the driver removes what interrupted attempts
of its tasks left in the dataset (uncommitted attempt files, stale ``*.tmp-*`` files) and says so.
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import platform
import socket
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from datagen.engine.worker import TaskBody, TaskOutcome, execute_task
from datagen.errors import ConfigError, DatagenError
from datagen.pipeline.refine.factory import network_hosting
from datagen.pipeline.step_timing import step_totals
from datagen.pipeline.viewspace import build_view_space
from jobs.ledger import CANCELLED, DONE, FAILED, FINAL_STATES, PENDING, RUNNING, Holders, Job, Ledger
from schemas.config import GenerationConfig
from schemas.dataset import DATASET_FILE, DatasetInfo
from schemas.index import CommitRecord, failure_record
from schemas.jobs import JobSpec, TaskSpec
from schemas.version import SCHEMA_VERSION
from storage import (
    Location,
    check_store,
    existing_info,
    finalise,
    init_dataset,
    open_location,
    read_info,
    storage_failure,
    sweep_orphans,
    sweep_temporaries,
    write_failure,
)
from storage.dataset import line_failure_id, read_tasks, record_of, retire_line_failures

LEASE_SECONDS = 120.0
RENEW_EVERY = 20.0
TASK_RETRIES = 3
"""Ray re-executions of a task whose worker process died (system failures, not bad input)."""
WAIT_POLL = 1.0
"""Seconds between looks at the ledger while other drivers hold the job's last tasks."""
TEMPORARY_AGE = 60.0
"""A temporary file older than this has no writer left (a write publishes within a moment)."""


@dataclass
class JobProgress:
    """What the driver reports while a job runs (for the progress display)."""

    total: int
    done: int = 0
    failed: int = 0
    samples: int = 0
    messages: list[str] = field(default_factory=list)
    waiting: str = ""
    """What the driver waits for when other drivers hold the job's remaining tasks ('' otherwise)."""
    warnings: set[str] = field(default_factory=set)
    """What the tasks this driver ran said of their objects (a flat mesh), once each."""


ProgressCallback = Callable[[JobProgress], None]


CLIENT_SESSION_WAIT = 120.0
"""Seconds a connection to a Ray client server waits out a refusal of a new client: after its driver was
killed, the server holds the lost driver's session for up to a minute (measured: a client 10 s after a
SIGKILL is refused after 45 s, one 55 s after succeeds), and a `datagen resume` right away must work."""
CLIENT_REFUSAL = "Initialization failure from server"
"""How Ray's client says the server refused to start its session (the reason, if any, follows)."""


def ensure_ray(address: str | None, num_cpus: int | None, notice: Callable[[str], None] | None = None) -> None:
    """Connect to a cluster (address or RAY_ADDRESS) or start a local Ray once per process.

    A Ray client server that refuses the session (it still holds a lost driver's) is asked again until
    `CLIENT_SESSION_WAIT` has passed, ``notice`` told once with how long; a refusal past that, or a
    client port that does not answer, is one `DatagenError` line with Ray's whole reason.
    """
    import ray

    if ray.is_initialized():
        return
    env = {"env_vars": {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
    if address:
        deadline = time.monotonic() + CLIENT_SESSION_WAIT
        told = False
        while True:
            try:
                ray.init(address=address, runtime_env=env, log_to_driver=False, logging_level=logging.ERROR)
                return
            except ValueError as exc:  # a ray:// address without Ray's client extra installed
                if "ray[client]" not in str(exc):
                    raise
                raise DatagenError(
                    f"{address}: Ray's client is not installed here; pip install 'ray[client]=={ray.__version__}' "
                    "(or this project with its cluster extra)"
                ) from None
            except ConnectionError as exc:  # the client port does not answer, or the server refuses us
                reason = " ".join(str(exc).split())
                refused = CLIENT_REFUSAL in reason
                if not refused or time.monotonic() >= deadline:
                    raise DatagenError(
                        f"cannot reach the Ray cluster at {address}: {reason or type(exc).__name__}"
                    ) from None
                if not told and notice is not None:
                    left = max(0.0, deadline - time.monotonic())
                    notice(
                        f"the Ray client server at {address} refused a new session (it may still hold a lost "
                        f"driver's); asking again for up to {left:.0f} s"
                    )
                    told = True
                _shutdown_client(ray)
                time.sleep(min(5.0, max(0.0, deadline - time.monotonic())))
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


def _waiting_notice(progress: ProgressCallback | None, total: int) -> Callable[[str], None] | None:
    """A notice for the progress display's waiting line (what `datagen submit|resume` print once)."""
    if progress is None:
        return None
    return lambda text: progress(JobProgress(total=total, waiting=text))


def _shutdown_client(ray: Any) -> None:
    """Forget a half-made client connection before asking again (Ray keeps some state after a failed init)."""
    try:
        ray.shutdown()
    except Exception:  # nothing was connected: nothing to forget
        return


def _remote_execute(
    body: TaskBody,
    task: TaskSpec,
    config: GenerationConfig,
    out: str,
    attempt_id: str,
    storage_options: dict[str, Any] | None,
    device: str,
    config_hash: str,
    schema_version: int,
    hosts: str = "",
) -> tuple[TaskOutcome, str]:
    """``body`` in a Ray task; with ``hosts`` (the name prefix of the job's shared refiner hosts) its
    network runs on its node's host, or, on a node without one, in the task on the CPU."""
    import ray

    network = None
    if hosts:
        from datagen.engine.refiner_host import node_network

        network = node_network(hosts)
        device = device if network is not None else "cpu"
    outcome = body(task, config, out, attempt_id, storage_options, device, config_hash, schema_version, network)
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
    commit = generator_commit()
    if commit:
        versions["datagen_commit"] = commit
    return DatasetInfo(
        schema_version=SCHEMA_VERSION,
        config=config,
        config_hash=config.config_hash(),
        view_positions=[(float(x), float(y), float(z)) for x, y, z in view_space.positions.tolist()],
        versions=versions,
        created=datetime.now(UTC).isoformat(timespec="seconds"),
    )


def generator_commit() -> str:
    """The git commit of the datagen source that runs (``<40 hex>``, ``+dirty`` when it has uncommitted
    changes), for a dataset's provenance; empty for an installed release, which its version names."""
    source = Path(__file__).resolve().parents[2]
    if not (source / ".git").exists():
        return ""
    try:
        head = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+dirty" if dirty else "")


def run_job(
    ledger: Ledger,
    job_id: str,
    address: str | None = None,
    num_cpus: int | None = None,
    storage_options: dict[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    max_in_flight: int | None = None,
    refiner_gpus: float = 0.0,
    wait_for_others: bool = True,
    body: TaskBody = execute_task,
    shared_refiner: bool = False,
    refiner_batch: int = 1,
    out: str | None = None,
) -> Job:
    """Run every runnable task of a job to completion (or cancellation); returns the job.

    ``out`` writes the tasks to another copy of the job's dataset than the one it was submitted
    with (`datagen shards repair` of a dataset moved since); None: the job's own.

    Each task reserves one CPU, and ``refiner_gpus`` of a GPU when that is > 0 (its learned refiner
    then runs on CUDA). Tasks are plain Ray tasks rather than a fixed pool of actors, so a node that
    joins or leaves mid-job simply gains or loses tasks; the refiner's weights are still loaded once
    per worker process, which Ray keeps between tasks.

    With ``wait_for_others`` the call returns only when the job is finished or cancelled, also when
    other drivers hold some of its tasks; without it, it returns as soon as it can claim nothing.
    ``body`` is what each task runs (`datagen.engine.worker.TaskBody`): `execute_task` unless the
    engine alone is measured or tested. ``shared_refiner`` puts a POCO refiner's network in one host
    per node (on its GPU with ``refiner_gpus`` > 0), which runs the jobs of every task there,
    ``refiner_batch`` jobs per encoder call (`datagen.engine.refiner_host`); tasks then reserve no GPU.
    """
    import ray

    job = ledger.job(job_id)
    spec = JobSpec.model_validate(job.spec)
    config = spec.config
    total = sum(ledger.task_counts(job_id).values())
    target = out or job.out
    location, info = check_output(target, config, storage_options)
    with _store_errors(target):
        info = init_dataset(location, info)  # an existing dataset keeps its own layout version
        # This job's objects-file lines say what is missing now: a line fixed since an earlier job of
        # the same file no longer is, so that job's records of the file's lines are retired first.
        retire_line_failures(location, spec.objects_file)
        for line_error in spec.line_errors:
            origin, _, message = line_error.partition(": ")
            write_failure(location, failure_record(line_failure_id(origin), message, origin=origin))
    ensure_ray(address, num_cpus, _waiting_notice(progress, total))
    if refiner_gpus > 0 and not ray.cluster_resources().get("GPU", 0):
        raise ConfigError(
            f"refiner_gpus = {refiner_gpus:g} but the Ray cluster has no GPU; drop --refiner-gpus to refine on CPU"
        )
    owner = f"driver-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    ledger.start_job(job_id, owner, LEASE_SECONDS)
    hosts: list[Any] = []
    try:
        device = "cuda" if refiner_gpus > 0 else "cpu"
        prefix = ""
        hosting = network_hosting(config)
        if shared_refiner and hosting is not None and hosting.shares(config):
            from datagen.engine.refiner_host import start_hosts

            prefix = f"datagen-refiner-{owner}"
            hosts = start_hosts(config, prefix, device, refiner_batch)
        task_gpus = 0.0 if hosts else refiner_gpus
        remote = ray.remote(num_cpus=1, num_gpus=task_gpus, max_retries=TASK_RETRIES, retry_exceptions=False)(
            _remote_execute
        )
        capacity = max_in_flight or max(1, int(ray.cluster_resources().get("CPU", 1)))
        state = JobProgress(total=total)
        _count(ledger, job_id, state)
        in_flight: dict[Any, tuple[TaskSpec, str]] = {}
        """Ray reference -> the task and the attempt it runs: the only tasks the driver holds."""
        last_renew = time.monotonic()
        cancelled = False
        while True:
            job_state = ledger.job_state(job_id)
            if job_state == CANCELLED:
                cancelled = True
                for ref in in_flight:
                    ray.cancel(ref, force=True)
                break
            free = capacity - len(in_flight)
            if free > 0:
                for claim in ledger.claim(job_id, owner, LEASE_SECONDS, free):
                    task = TaskSpec.model_validate(claim.task.spec)
                    ref = remote.remote(
                        body,
                        task,
                        config,
                        target,
                        claim.attempt_id,
                        storage_options,
                        device,
                        info.config_hash,
                        info.schema_version,
                        prefix,
                    )
                    in_flight[ref] = (task, claim.attempt_id)
            if in_flight:
                state.waiting = ""
                ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=1.0)
                for ref in ready:
                    task, attempt_id = in_flight.pop(ref)
                    _record(ledger, job_id, task, attempt_id, ref, state, location)
            else:
                counts = ledger.task_counts(job_id)
                if not counts.get(PENDING) and not counts.get(RUNNING):
                    break  # finished, by this driver or others
                if not wait_for_others or job_state in FINAL_STATES:
                    break
                # Other drivers hold the remaining tasks: wait for them to finish (or for one of
                # them to be lost, when the claim above takes its tasks over).
                holders = ledger.holders(job_id)
                state.waiting = waiting_line(job_id, holders) if holders else ""
                time.sleep(WAIT_POLL)
            _count(ledger, job_id, state)
            if progress:
                progress(state)
            if time.monotonic() - last_renew > RENEW_EVERY:
                ledger.renew(job_id, owner, LEASE_SECONDS)
                last_renew = time.monotonic()
        counts = ledger.task_counts(job_id)
        if not cancelled and not counts.get(PENDING) and not counts.get(RUNNING):
            summary = _finish(ledger, job_id, spec, location, state.warnings)
            ledger.finish_job(job_id, summary, other_failures=len(spec.line_errors))
        state.waiting = ""
        _count(ledger, job_id, state)
        if progress:
            progress(state)
    finally:
        ledger.leave(job_id, owner)
        if hosts:
            from datagen.engine.refiner_host import stop_hosts

            stop_hosts(hosts)
    return ledger.job(job_id)


def waiting_line(job_id: str, holders: Holders) -> str:
    """One line: what a driver waits for (the tasks others hold) and until when."""
    who = [f"driver {d.describe()} (alive)" for d in holders.live] + holders.unknown
    shown = ", ".join(who[:3]) + (f" and {len(who) - 3} more" if len(who) > 3 else "")
    tasks = f"{holders.tasks} task{'s' if holders.tasks != 1 else ''}"
    line = f"job {job_id}: waiting for {tasks} held by {shown}"
    if holders.unknown:
        until = time.strftime("%H:%M:%S", time.localtime(holders.until))
        line += f"; until they finish, or their leases lapse at {until} unless renewed"
    else:
        line += "; until they finish (a driver that dies is replaced at once)"
    return line


def _count(ledger: Ledger, job_id: str, state: JobProgress) -> None:
    """The job's progress from the ledger: every driver's work, not only this one's (a few rows of
    the counts the ledger keeps, whatever the job's size)."""
    counts = ledger.task_counts(job_id)
    state.done = counts.get(DONE, 0)
    state.failed = counts.get(FAILED, 0)
    state.samples = ledger.done_samples(job_id)


def _finish(
    ledger: Ledger, job_id: str, spec: JobSpec, location: Location, warnings: set[str] | None = None
) -> dict[str, Any]:
    """Finalise the index and clean up leftovers; the job's summary, counted from the dataset, with
    the ``warnings`` this driver's tasks gave."""
    with _store_errors(location.url):
        finalised = finalise(location)  # reads the records of the tasks its manifest does not name yet
        commits = [record_of(row) for row in read_tasks(location, finalised.manifest).to_pylist()]
    task_ids = ledger.task_ids(job_id)
    job_tasks = set(task_ids)
    summary: dict[str, Any] = {"step_seconds": step_totals(r for r in commits if r.task_id in job_tasks).to_json()}
    try:
        swept = sweep_leftovers(location, task_ids, commits)
    except Exception as error:  # a failed clean-up must not fail a finished job
        summary["sweep_error"] = f"{type(error).__name__}: {error}"
        swept = []
    counts = ledger.task_counts(job_id)
    failed = [(TaskSpec.model_validate(t.spec), t.error) for t in ledger.each_task(job_id, (FAILED,))]
    summary.update(
        {
            "tasks": sum(counts.values()),
            "done": counts.get(DONE, 0),
            "failed": counts.get(FAILED, 0),
            "refused_lines": len(spec.line_errors),
            "samples": finalised.num_samples,
            "line_errors": spec.line_errors,
            "warnings": sorted(warnings or ()),
            "failures": [f"{task.object.origin}: {task.task_id}: {error}" for task, error in failed],
            "swept": len(swept),
            "swept_examples": swept[:5],
        }
    )
    return summary


def sweep_leftovers(location: Location, task_ids: list[str], commits: list[CommitRecord] | None = None) -> list[str]:
    """Remove what interrupted attempts of these finished tasks left (attempt files no commit names,
    temporary files older than `TEMPORARY_AGE`); the removed paths, sorted. Only for a job whose
    tasks are all finished: no attempt of theirs is still writing."""
    return sorted(sweep_orphans(location, task_ids, commits) + sweep_temporaries(location, TEMPORARY_AGE))


def check_output(
    url: str, config: GenerationConfig, storage_options: dict[str, Any] | None = None
) -> tuple[Location, DatasetInfo]:
    """Whether a job of ``config`` may write to ``url``, read-only: the store answers (a wrong endpoint,
    key or bucket: one line in seconds), and a dataset already there has this config and the same
    files. (its location, the dataset info a job would write). Called before a job is recorded, so a
    refused one never lingers in the ledger against the dataset it would have spoiled."""
    location = open_location(url, storage_options)
    info = dataset_info(config)
    with _store_errors(url):
        check_store(location)
        _check_same_files(location, config, info.config_hash)
        existing_info(location, info)
    return location, info


def _check_same_files(location: Location, config: GenerationConfig, config_hash: str) -> None:
    """Refuse a dataset made with this very config but other contents of the files it names (new
    shipped POCO weights after an upgrade, an edited view-space file): running on would mix samples
    of two refiners (or view spaces) in one dataset. `init_dataset` refuses any other config."""
    if not location.exists(DATASET_FILE):
        return
    existing = read_info(location)
    if existing.config != config or existing.config_hash == config_hash:
        return
    files = ", ".join(f"{name} = {path}" for name, path in config.named_files().items())
    raise ConfigError(
        f"{location.url}: was made with this config but other contents of the files it names "
        f"(config hash {existing.config_hash[:12]} there, {config_hash[:12]} now; {files}); one changed since, "
        "such as the built-in POCO weights after an upgrade: restore the files it was made with, "
        "or write to a new --out"
    )


@contextmanager
def _store_errors(url: str) -> Iterator[None]:
    """The driver's own store operations: any failure of the store (refused credentials, an
    unreachable endpoint once its timeout and retries are spent) becomes one `StorageError` line."""
    try:
        yield
    except DatagenError:
        raise  # already one line (a StorageError, or a refusal such as `_check_same_files`)
    except Exception as error:  # botocore, aiohttp and fsspec raise many unrelated types
        raise storage_failure(url, error) from None


def _record(
    ledger: Ledger,
    job_id: str,
    task: TaskSpec,
    attempt_id: str,
    ref: Any,
    state: JobProgress,
    location: Location,
) -> None:
    import ray

    task_id = task.task_id
    try:
        outcome, placement = ray.get(ref)
    except ray.exceptions.TaskCancelledError:
        ledger.release(job_id, task_id, attempt_id)
        return
    except ray.exceptions.RayError as exc:
        # Ray's retries are spent (its workers died), or the task raised (a bug, or the store failed
        # under it): the task is failed with the reason, so the job ends and says why, and the
        # dataset gets the failure record the worker could not write.
        message = _worker_failure(exc, job_id)
        if ledger.fail(job_id, task_id, attempt_id, f"worker error: {message}"):
            state.messages.append(f"{task_id}: {message}")
            _write_failure(location, task, message, state)
        return
    state.warnings.update(outcome.warnings)
    if outcome.ok:
        ledger.complete(job_id, task_id, attempt_id, outcome.samples, placement)
    elif ledger.fail(job_id, task_id, attempt_id, outcome.message):
        state.messages.append(f"{task_id}: {outcome.message}")


def _worker_failure(exc: BaseException, job_id: str) -> str:
    """One line: what happened to the task's worker, and what to do."""
    import ray

    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else exc
        text = str(cause).strip().splitlines()
        detail = f"{type(cause).__name__}: {text[-1] if text else 'no message'}"
        return (
            f"the task raised {detail}; if the output store failed (disk full, permissions) fix it, "
            f"otherwise it is a bug to report; then run `datagen resume {job_id}`"
        )
    text = str(exc).strip().splitlines()
    detail = text[-1] if text else type(exc).__name__
    return (
        f"its worker process died {TASK_RETRIES + 1} times running it ({type(exc).__name__}: {detail}); "
        f"usually out of memory: run with fewer --workers or on nodes with more memory, then `datagen resume {job_id}`"
    )


def _write_failure(location: Location, task: TaskSpec, message: str, state: JobProgress) -> None:
    try:
        failure = failure_record(task.task_id, message, object_name=task.object.name, origin=task.object.origin)
        write_failure(location, failure)
    except Exception as error:  # the store that failed the task may refuse this too; the ledger has it
        state.messages.append(f"{task.task_id}: failure record not written ({type(error).__name__}: {error})")
