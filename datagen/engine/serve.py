"""The serve loop: a long-running driver that takes queued jobs from the ledger and runs them.

``datagen serve`` is a thin layer over `serve`; from Python::

    from datagen.engine.serve import serve
    serve(RunSettings(home=...), once=True)

Several serve loops (on one or several machines' Ray clusters) may share one ledger: each job's
tasks are claimed under leases, so a task runs once. A job whose remaining tasks other drivers hold
is not run again until one of them can be claimed: a driver of this machine that died is noticed at
once (its tasks are taken over), one elsewhere when its leases lapse.

The loop reports what it does as lines of text, the same lines ``datagen serve`` prints:
``report`` gets ``serving LEDGER``, ``running job ID``, ``job ID: STATE`` and, once per job and set
of holders, ``job ID: waiting for N tasks held by ...; until ...`` (what it waits for and until
when); ``error`` gets ``error: job ID: MESSAGE`` for a job that could not run (it is failed in the
ledger with that message, and the loop goes on).

With ``once`` the loop returns when nothing is left that it could do: no job is runnable, or every
unfinished job's remaining tasks are held by drivers it sees alive on this machine (they finish
them; it says so in one line). It waits for holders it cannot see (another machine, an unknown
owner), since their tasks become its own if their leases lapse.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from datagen.engine.driver import run_job, waiting_line
from datagen.settings import RunSettings, ledger_for
from jobs.ledger import FINAL_STATES, Holders, LedgerError
from schemas.errors import DatagenError

Report = Callable[[str], None]
"""Receives one line of text (no newline)."""


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
    nothing is left to do: see the module's docstring).

    A job that cannot start or fails with a user error (a `DatagenError`: bad config, unreachable
    store, ...) is failed in the ledger and reported through ``error``; the loop goes on. A
    `LedgerError` (the ledger itself cannot be used) and any bug stop the loop and propagate.
    When a job comes back unfinished (other drivers hold its remaining tasks), or nothing is
    runnable, the loop sleeps ``poll`` seconds before it looks again.
    """
    ledger = ledger_for(settings)
    said: dict[str, str] = {}
    """job id -> the holders last reported for it (a waiting line is reported once per holders)."""
    try:
        report(f"serving {ledger.path}")
        while True:
            jobs = ledger.runnable_jobs()
            waiting = not jobs
            left_to_others = 0
            for job in jobs:
                holders = ledger.holders(job.job_id)
                if holders is not None:
                    who = " ".join(sorted([d.driver_id for d in holders.live] + holders.unknown))
                    if said.get(job.job_id) != who:
                        report(_held_line(job.job_id, holders, once))
                        said[job.job_id] = who
                    if once and not holders.unknown:
                        left_to_others += 1
                    waiting = True
                    continue
                said.pop(job.job_id, None)
                report(f"running job {job.job_id}")
                try:
                    finished = run_job(
                        ledger,
                        job.job_id,
                        address=settings.ray_address,
                        num_cpus=settings.num_workers,
                        refiner_gpus=settings.refiner_gpus,
                        shared_refiner=settings.shared_refiner,
                        refiner_batch=settings.refiner_batch,
                        storage_options=settings.storage_options(job.out),
                        wait_for_others=False,
                    )
                except LedgerError:
                    raise
                except DatagenError as exc:
                    finished = ledger.fail_job(job.job_id, str(exc))
                    error(f"error: job {job.job_id}: {exc}")
                report(f"job {finished.job_id}: {finished.state}")
                # Unfinished: other drivers hold its remaining tasks; look again after a pause.
                waiting = waiting or finished.state not in FINAL_STATES
            if once and len(ledger.runnable_jobs()) <= left_to_others:
                break
            if waiting:
                time.sleep(poll)
    finally:
        ledger.close()


def _held_line(job_id: str, holders: Holders, once: bool) -> str:
    """What the loop waits for on a job whose remaining tasks others hold (or, with ``once`` and
    only live drivers of this machine holding them, that it leaves the job to them)."""
    if once and not holders.unknown:
        who = ", ".join(f"driver {d.describe()}" for d in holders.live)
        tasks = f"{holders.tasks} task{'s' if holders.tasks != 1 else ''}"
        them = "them" if len(holders.live) > 1 else "it"
        return f"job {job_id}: its last {tasks} run under {who} (alive); leaving the job to {them}"
    return waiting_line(job_id, holders)
