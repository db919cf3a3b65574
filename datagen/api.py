"""The Python API, mirroring the CLI: `submit`, `status`, `cancel`, `resume`, `serve` for notebooks."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from datagen.config_io import load_config
from datagen.engine import serve as serve_loop
from datagen.engine.driver import ProgressCallback, check_output, run_job
from datagen.engine.job_plan import plan_job
from datagen.engine.worker import TaskBody, execute_task
from datagen.errors import DatagenError, ObjectsFileError
from datagen.settings import LEDGER_FILE, RunSettings, ledger_for
from jobs.ledger import Job, LedgerError
from schemas.config import GenerationConfig

__all__ = ["LEDGER_FILE", "cancel", "default_out", "enqueue", "ledger_for", "resume", "serve", "status", "submit"]


def default_out(settings: RunSettings, job_id: str) -> str:
    return str(Path(settings.home) / "datasets" / job_id)


def enqueue(
    objects: str | Path,
    config: GenerationConfig | str | Path | None = None,
    settings: RunSettings | None = None,
    strict: bool = False,
    on_line_error: Callable[[str], None] | None = None,
) -> Job:
    """Plan a job and put it in the ledger (pending) without running it.

    Every objects-file line's mesh file is read while planning; a line that names no usable object
    (a missing file, a bad option) is told to ``on_line_error`` at once and left out of the job, or,
    with ``strict``, refuses the whole job before anything is recorded."""
    settings = settings or RunSettings()
    resolved = config if isinstance(config, GenerationConfig) else load_config(config)
    plan = plan_job(objects, resolved, out="")
    errors = plan.spec.line_errors
    if errors and strict:
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        raise ObjectsFileError(f"{errors[0]}{more}; fix the line or submit without --strict to go on without it")
    for error in errors:
        if on_line_error is not None:
            on_line_error(error)
    out = settings.out or default_out(settings, plan.spec.job_id)
    check_output(out, resolved, settings.storage_options(out))  # refused before anything is recorded
    spec = plan.spec.model_copy(update={"out": out})
    with_ledger = ledger_for(settings)
    try:
        return with_ledger.create_job(spec.job_id, spec.model_dump(mode="json"), out, plan.tasks.rows())
    finally:
        with_ledger.close()


def submit(
    objects: str | Path,
    config: GenerationConfig | str | Path | None = None,
    settings: RunSettings | None = None,
    progress: ProgressCallback | None = None,
    storage_options: dict[str, Any] | None = None,
    body: TaskBody = execute_task,
) -> Job:
    """Plan and run a job now (local Ray unless ``settings.ray_address``); returns the finished job.
    ``body`` is what each task runs (`datagen.engine.worker.TaskBody`; the engine's benchmarks and
    tests pass `datagen.engine.worker.empty_task`)."""
    settings = settings or RunSettings()
    job = enqueue(objects, config, settings)
    return resume(job.job_id, settings, progress, storage_options, body=body)


def resume(
    job_id: str,
    settings: RunSettings | None = None,
    progress: ProgressCallback | None = None,
    storage_options: dict[str, Any] | None = None,
    body: TaskBody = execute_task,
) -> Job:
    """Run what is not done of a job; finished tasks are kept, never recomputed.

    Tasks a live driver still runs (another `submit`, `resume` or `serve` on this job) stay with it:
    this call shares the rest of the work, waits for the job's end and returns it finished, with a
    summary counting the whole dataset (`datagen.engine.driver.run_job`)."""
    settings = settings or RunSettings()
    ledger = ledger_for(settings)
    try:
        job = ledger.reopen_job(job_id)
        options = storage_options if storage_options is not None else settings.storage_options(job.out)
        try:
            return run_job(
                ledger,
                job_id,
                address=settings.ray_address,
                num_cpus=settings.num_workers,
                storage_options=options,
                refiner_gpus=settings.refiner_gpus,
                shared_refiner=settings.shared_refiner,
                refiner_batch=settings.refiner_batch,
                progress=progress,
                body=body,
            )
        except LedgerError:
            raise  # the ledger itself cannot be used: nothing to record the failure in
        except DatagenError as exc:
            ledger.fail_job(job_id, str(exc))  # a job that cannot start does not linger as pending
            raise
    finally:
        ledger.close()


def cancel(job_id: str, settings: RunSettings | None = None) -> Job:
    ledger = ledger_for(settings or RunSettings())
    try:
        return ledger.cancel_job(job_id)
    finally:
        ledger.close()


def status(job_id: str | None = None, settings: RunSettings | None = None) -> list[Job]:
    ledger = ledger_for(settings or RunSettings())
    try:
        return [ledger.job(job_id)] if job_id else ledger.jobs()
    finally:
        ledger.close()


def serve(
    settings: RunSettings | None = None,
    *,
    poll: float = 2.0,
    once: bool = False,
    report: serve_loop.Report = print,
    error: serve_loop.Report = serve_loop.print_error,
) -> None:
    """Take queued jobs from the ledger in order and run them, as ``datagen serve`` does; with
    ``once``, return when no job is runnable. See `datagen.engine.serve.serve`."""
    serve_loop.serve(settings or RunSettings(), poll=poll, once=once, report=report, error=error)
