"""The Python API, mirroring the CLI: `submit`, `status`, `cancel`, `resume` for notebooks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from datagen.config_io import load_config
from datagen.engine.driver import ProgressCallback, run_job
from datagen.engine.job_plan import plan_job
from datagen.errors import DatagenError
from datagen.settings import RunSettings
from jobs.ledger import Job, Ledger
from schemas.config import GenerationConfig
from storage.location import StorageError

LEDGER_FILE = "ledger.db"


def ledger_for(settings: RunSettings) -> Ledger:
    return Ledger(Path(settings.home) / LEDGER_FILE)


def default_out(settings: RunSettings, job_id: str) -> str:
    return str(Path(settings.home) / "datasets" / job_id)


def enqueue(
    objects: str | Path,
    config: GenerationConfig | str | Path | None = None,
    settings: RunSettings | None = None,
) -> Job:
    """Plan a job and put it in the ledger (pending) without running it."""
    settings = settings or RunSettings()
    resolved = config if isinstance(config, GenerationConfig) else load_config(config)
    plan = plan_job(objects, resolved, out="")
    out = settings.out or default_out(settings, plan.job_id)
    plan = plan.model_copy(update={"out": out})
    tasks = [(t.task_id, t.model_dump(mode="json")) for t in plan.tasks]
    with_ledger = ledger_for(settings)
    try:
        return with_ledger.create_job(plan.job_id, plan.model_dump(mode="json"), out, tasks)
    finally:
        with_ledger.close()


def submit(
    objects: str | Path,
    config: GenerationConfig | str | Path | None = None,
    settings: RunSettings | None = None,
    progress: ProgressCallback | None = None,
    storage_options: dict[str, Any] | None = None,
) -> Job:
    """Plan and run a job now (local Ray unless ``settings.ray_address``); returns the finished job."""
    settings = settings or RunSettings()
    job = enqueue(objects, config, settings)
    return resume(job.job_id, settings, progress, storage_options)


def resume(
    job_id: str,
    settings: RunSettings | None = None,
    progress: ProgressCallback | None = None,
    storage_options: dict[str, Any] | None = None,
) -> Job:
    """Run what is not done of a job; finished tasks are kept, never recomputed."""
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
                progress=progress,
            )
        except (DatagenError, StorageError) as exc:
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
