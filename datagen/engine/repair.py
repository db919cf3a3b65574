"""`datagen shards repair`: re-run exactly the damaged tasks of a dataset, then finalise its index.

The damaged tasks are those `storage.validate` names (a shard with a lost or truncated chunk file,
an unreadable fragment or commit record, a commit record lost from under the finalised index) plus
the tasks the ledger has done that have no commit record left. Their records are withdrawn
(`storage.checks.withdraw`: readers then serve the sound rest, nothing half written), the ledger
makes exactly them pending again, and the job's own driver (`run_job`) re-runs them with the job's
stored config and objects: by determinism the same samples as before the damage. A dataset whose
only problem is its merged index just gets it finalised again; a sound one is left untouched.

The tasks come from the job ledger that made the dataset (its config and objects are there), so
repair runs where the job was submitted: the same ``--home`` (on a cluster, the head). The jobs are
found by the dataset's own identity, the config hash of its ``dataset.json``, wherever the data now
lives (a copied or moved dataset is repaired in place, from the jobs that made its original); a job
that wrote to this very path is preferred, and only those jobs' done tasks are missed when their
commit records are gone (a copy may rightly hold fewer tasks than its original).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from datagen.engine.driver import ProgressCallback, run_job
from datagen.settings import RunSettings, ledger_for
from jobs.ledger import DONE, Job, Ledger
from schemas.jobs import JobSpec
from storage import (
    Location,
    StorageError,
    check_store,
    finalise,
    open_location,
    read_commits,
    read_info,
    validate_dataset,
)
from storage.checks import Findings, sort_problems, withdraw
from storage.dataset import Problem

LOST_COMMIT = "commit record missing although the ledger has the task done"


@dataclass(frozen=True)
class RepairSummary:
    url: str
    repaired: dict[str, str] = field(default_factory=dict)
    """task id -> the first problem that made it re-run."""
    index_problems: list[Problem] = field(default_factory=list)
    """Problems of the merged index alone (mended by finalising it again)."""
    jobs: list[str] = field(default_factory=list)
    samples: int = 0
    """Samples of the repaired dataset."""

    @property
    def sound(self) -> bool:
        """Nothing was wrong: nothing was touched."""
        return not self.repaired and not self.index_problems


def repair_dataset(url: str, settings: RunSettings, progress: ProgressCallback | None = None) -> RepairSummary:
    """Find the damage, withdraw and re-run the damaged tasks, finalise, check again.

    Raises `StorageError` when the store cannot be used, when a problem cannot be mended by
    re-running tasks (``dataset.json`` damaged), when no job of the ledger made a damaged task, or
    when the dataset is still not sound afterwards.
    """
    options = settings.storage_options(url)
    location = open_location(url, options)
    check_store(location)
    found = sort_problems(validate_dataset(url, full=True, storage_options=options).problems)
    if found.other:
        raise StorageError(f"{url}: cannot be repaired by re-running tasks: {found.other[0]}")
    ledger = ledger_for(settings)
    try:
        here = _jobs_writing(ledger, url)
        jobs = here + [job for job in _jobs_of_config(ledger, read_info(location).config_hash) if job not in here]
        redo = {task: problems[0].line for task, problems in found.tasks.items()} | _lost_commits(
            ledger, here, location
        )
        if not redo and not found.index:
            return RepairSummary(url, jobs=[j.job_id for j in here], samples=_samples(url, options))
        owners = _owners(ledger, jobs, sorted(redo), url, settings, found)
        withdraw(location, sorted(redo))
        for job_id in sorted(set(owners.values())):
            ledger.redo_tasks(job_id, sorted(task for task, owner in owners.items() if owner == job_id))
            run_job(
                ledger,
                job_id,
                address=settings.ray_address,
                num_cpus=settings.num_workers,
                storage_options=options,
                progress=progress,
                refiner_gpus=settings.refiner_gpus,
                shared_refiner=settings.shared_refiner,
                refiner_batch=settings.refiner_batch,
                out=url,
            )
        finalise(location)
        not_done = sorted(
            task.task_id
            for job_id in set(owners.values())
            for task in ledger.tasks(job_id)
            if task.task_id in redo and task.state != DONE
        )
        if not_done:
            raise StorageError(f"{url}: the re-run of tasks {not_done} did not finish; see `datagen status`")
        after = validate_dataset(url, full=True, storage_options=options).problems
        if after:
            raise StorageError(f"{url}: still not sound after the repair ({len(after)} problems): {after[0]}")
        return RepairSummary(url, redo, found.index, sorted(set(owners.values())), _samples(url, options))
    finally:
        ledger.close()


def _where(url: str) -> tuple[str, str]:
    """(protocol, root) of a dataset URL, so a relative local path matches the ledger's absolute one."""
    location = open_location(url)
    protocol = location.fs.protocol if isinstance(location.fs.protocol, str) else location.fs.protocol[0]
    root = os.path.abspath(location.root) if location.is_local else location.root.strip("/")
    return protocol, root


def _jobs_writing(ledger: Ledger, url: str) -> list[Job]:
    where = _where(url)
    return [job for job in ledger.jobs() if job.out and _where(job.out) == where]


def _jobs_of_config(ledger: Ledger, config_hash: str) -> list[Job]:
    """The ledger's jobs whose config is the dataset's (by its hash in ``dataset.json``): the jobs that
    could have made it, wherever it was written."""
    found = []
    for job in ledger.jobs():
        try:
            if JobSpec.model_validate(job.spec).config.config_hash() == config_hash:
                found.append(job)
        except (ValueError, OSError):  # a job of an older datagen, or one naming files gone since
            continue
    return found


def _lost_commits(ledger: Ledger, jobs: list[Job], location: Location) -> dict[str, str]:
    """Tasks the ledger has done whose commit record is gone (never named by a finalised index,
    so `storage.validate` cannot see that they are missing)."""
    committed, _ = read_commits(location)
    names = {r.task_id for r in committed}
    return {
        task.task_id: LOST_COMMIT
        for job in jobs
        for task in ledger.tasks(job.job_id)
        if task.state == DONE and task.task_id not in names
    }


def _owners(
    ledger: Ledger, jobs: list[Job], tasks: list[str], url: str, settings: RunSettings, found: Findings
) -> dict[str, str]:
    """task id -> the job that plans it; `StorageError` for a task no job of this ledger plans."""
    owners = {task.task_id: job.job_id for job in jobs for task in ledger.tasks(job.job_id)}
    unknown = [task for task in tasks if task not in owners]
    if unknown:
        example = found.tasks.get(unknown[0], [""])[0]
        raise StorageError(
            f"{url}: needs task {unknown[0]} run again ({example}), and no job of this dataset's config in the "
            f"ledger at {settings.home} plans it; give --home the ledger where the dataset was made (on a "
            "cluster, the head), or re-submit its objects to a new --out"
        )
    return {task: owners[task] for task in tasks}


def _samples(url: str, options: dict[str, object]) -> int:
    from storage import open_dataset

    return len(open_dataset(url, dict(options)))
