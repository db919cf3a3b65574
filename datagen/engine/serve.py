"""The serve loop: a long-running driver that takes queued jobs from the ledger and runs them.

``datagen serve`` is a thin layer over `serve`; from Python::

    from datagen.engine.serve import serve
    serve(RunSettings(home=...), once=True)

Several serve loops (on one or several machines' Ray clusters) may share one ledger: each job's
tasks are claimed under leases, so a task runs once, and a job another driver still holds is looked
at again after ``poll`` seconds.

The loop reports what it does as lines of text, the same lines ``datagen serve`` prints:
``report`` gets ``serving LEDGER``, ``running job ID`` and ``job ID: STATE``; ``error`` gets
``error: job ID: MESSAGE`` for a job that could not run (it is failed in the ledger with that
message, and the loop goes on).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

from datagen.engine.driver import run_job
from datagen.settings import RunSettings
from jobs.ledger import FINAL_STATES, Ledger, LedgerError
from schemas.errors import DatagenError

LEDGER_FILE = "ledger.db"
"""The ledger's file name inside the home folder (``RunSettings.home``)."""

Report = Callable[[str], None]
"""Receives one line of text (no newline)."""


def ledger_for(settings: RunSettings) -> Ledger:
    """The job ledger of a home folder (``HOME/ledger.db``), created when missing."""
    return Ledger(Path(settings.home) / LEDGER_FILE)


def print_error(line: str) -> None:
    """The default ``error`` callback: the line on stderr."""
    print(line, file=sys.stderr)


def serve(
    settings: RunSettings,
    *,
    poll: float = 2.0,
    once: bool = False,
    report: Report = print,
    error: Report = print_error,
) -> None:
    """Take runnable jobs in order and run each to its end, until stopped (or, with ``once``, until
    no job is runnable).

    A job that cannot start or fails with a user error (a `DatagenError`: bad config, unreachable
    store, ...) is failed in the ledger and reported through ``error``; the loop goes on. A
    `LedgerError` (the ledger itself cannot be used) and any bug stop the loop and propagate.
    When a job comes back unfinished (another driver holds its remaining tasks), or nothing is
    runnable, the loop sleeps ``poll`` seconds before it looks again.
    """
    ledger = ledger_for(settings)
    try:
        report(f"serving {ledger.path}")
        while True:
            jobs = ledger.runnable_jobs()
            waiting = not jobs
            for job in jobs:
                report(f"running job {job.job_id}")
                try:
                    finished = run_job(
                        ledger,
                        job.job_id,
                        address=settings.ray_address,
                        num_cpus=settings.num_workers,
                        refiner_gpus=settings.refiner_gpus,
                        storage_options=settings.storage_options(job.out),
                    )
                except LedgerError:
                    raise
                except DatagenError as exc:
                    finished = ledger.fail_job(job.job_id, str(exc))
                    error(f"error: job {job.job_id}: {exc}")
                report(f"job {finished.job_id}: {finished.state}")
                # Unfinished: another driver holds its remaining tasks; look again after a pause.
                waiting = waiting or finished.state not in FINAL_STATES
            if once and not ledger.runnable_jobs():
                break
            if waiting:
                time.sleep(poll)
    finally:
        ledger.close()
