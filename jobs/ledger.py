"""The job ledger: a SQLite (WAL) file of jobs and tasks that survives crashes.

States: ``pending -> running -> done | failed | cancelled`` for jobs and tasks alike. A running task
holds a lease (owner, expiry); a task whose lease expired (its driver died) can be claimed again,
with a new attempt id. Transitions are idempotent and conditional (a late report from an old
attempt cannot overwrite a newer one), and every multi-row change runs in one ``BEGIN IMMEDIATE``
transaction, so several processes can share one ledger file.

Liveness: each driver working on a job is recorded in ``drivers`` (its lease-owner name, host,
machine, PID, process start time) with a heartbeat it renews together with its leases, and leaves
(`leave`) when it stops. A driver is *lost* when its process is gone (decided at once on the same
machine, `jobs.liveness`) or, elsewhere, when it has not renewed its heartbeat for a lease period.
A lost driver's tasks can be claimed at once, without waiting for its leases to expire; `lost_driver`
tells `datagen status` that a running job has no live driver left.

Scale: a job of 100,000 tasks costs each call what it touches, not what the job holds. The task
counts (and samples) per state live in ``task_counts``, kept by triggers on every change of a
task's state or samples, whoever makes it; claims and the other per-tick queries read index ranges
of the states they need (pending, running), never every task of the job; a job's spec is small (its
tasks are rows of their own) and a task's spec is parsed only when asked for.
"""

from __future__ import annotations

import functools
import json
import sqlite3
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from jobs.liveness import ProcessIdentity, process_alive, process_identity
from schemas.errors import DatagenError

PENDING, RUNNING, DONE, FAILED, CANCELLED = "pending", "running", "done", "failed", "cancelled"
FINAL_STATES = (DONE, FAILED, CANCELLED)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    job_id TEXT PRIMARY KEY,
    state TEXT NOT NULL,
    spec TEXT NOT NULL,
    out TEXT NOT NULL,
    created REAL NOT NULL,
    updated REAL NOT NULL,
    owner TEXT,
    summary TEXT
);
CREATE TABLE IF NOT EXISTS tasks (
    job_id TEXT NOT NULL,
    task_id TEXT NOT NULL,
    position INTEGER NOT NULL,
    state TEXT NOT NULL,
    spec TEXT NOT NULL,
    attempts INTEGER NOT NULL DEFAULT 0,
    attempt_id TEXT,
    lease_owner TEXT,
    lease_expires REAL,
    error TEXT,
    placement TEXT,
    samples INTEGER,
    updated REAL NOT NULL,
    PRIMARY KEY (job_id, task_id)
);
CREATE INDEX IF NOT EXISTS tasks_by_state ON tasks (job_id, state, position);
CREATE TABLE IF NOT EXISTS drivers (
    driver_id TEXT PRIMARY KEY,
    job_id TEXT NOT NULL,
    host TEXT NOT NULL,
    machine TEXT NOT NULL,
    pid INTEGER NOT NULL,
    process_start TEXT NOT NULL,
    started REAL NOT NULL,
    heartbeat REAL NOT NULL,
    lease REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS drivers_by_job ON drivers (job_id);
CREATE TABLE IF NOT EXISTS task_counts (
    job_id TEXT NOT NULL,
    state TEXT NOT NULL,
    tasks INTEGER NOT NULL,
    samples INTEGER NOT NULL,
    PRIMARY KEY (job_id, state)
);
"""

_COUNT_NEW = (
    "INSERT INTO task_counts (job_id, state, tasks, samples) "
    "VALUES (new.job_id, new.state, 1, COALESCE(new.samples, 0)) "
    "ON CONFLICT (job_id, state) DO UPDATE SET tasks = tasks + 1, samples = samples + excluded.samples;"
)
_UNCOUNT_OLD = (
    "UPDATE task_counts SET tasks = tasks - 1, samples = samples - COALESCE(old.samples, 0) "
    "WHERE job_id = old.job_id AND state = old.state;"
)
_TRIGGERS = (
    f"CREATE TRIGGER IF NOT EXISTS count_inserted_task AFTER INSERT ON tasks BEGIN {_COUNT_NEW} END",
    f"CREATE TRIGGER IF NOT EXISTS count_deleted_task AFTER DELETE ON tasks BEGIN {_UNCOUNT_OLD} END",
    "CREATE TRIGGER IF NOT EXISTS count_changed_task AFTER UPDATE OF job_id, state, samples ON tasks "
    "WHEN old.job_id IS NOT new.job_id OR old.state IS NOT new.state OR old.samples IS NOT new.samples "
    f"BEGIN {_UNCOUNT_OLD} {_COUNT_NEW} END",
)
"""``task_counts`` follows every task row: tasks and their samples per job and state, so progress,
status and the end of a job read a handful of rows instead of counting every task."""

DEFAULT_LEASE = 120.0
"""Seconds a driver's leases (and heartbeat) stay valid without renewal, unless it says otherwise."""


class LedgerError(DatagenError):
    """The ledger cannot be opened, or a job id is unknown; the message says what to do."""


@dataclass(frozen=True)
class Job:
    job_id: str
    state: str
    spec: dict[str, Any]
    out: str
    created: float
    updated: float
    owner: str | None
    summary: dict[str, Any] | None


@dataclass(frozen=True)
class Task:
    job_id: str
    task_id: str
    position: int
    state: str
    spec_text: str = field(repr=False)
    """The task's spec as stored (sorted-key JSON); `spec` parses it when asked, so listing a job's
    100,000 tasks parses none."""
    attempts: int
    attempt_id: str | None
    lease_owner: str | None
    lease_expires: float | None
    error: str | None
    placement: str | None
    samples: int | None

    @functools.cached_property
    def spec(self) -> dict[str, Any]:
        return dict(json.loads(self.spec_text))


@dataclass(frozen=True)
class Driver:
    """A driver process working on a job, as recorded when it started and at its last heartbeat."""

    driver_id: str
    """The name it holds leases under (``Task.lease_owner``)."""
    job_id: str
    process: ProcessIdentity
    started: float
    heartbeat: float
    """Wall-clock time it last renewed its leases."""
    lease: float
    """Seconds its leases last without renewal: silent longer than this, it is lost."""

    def lost(self, now: float | None = None) -> bool:
        """Gone: its process is dead (same machine, known at once), or silent for a lease period."""
        alive = process_alive(self.process)
        if alive is not None:
            return not alive
        return (time.time() if now is None else now) - self.heartbeat > self.lease

    def describe(self) -> str:
        """``pid 123 on host``, for messages."""
        return f"pid {self.process.pid} on {self.process.host}"


@dataclass(frozen=True)
class LostDriver:
    """A running job none of whose drivers is alive (see `Ledger.lost_driver`)."""

    since: float
    """When it was last heard from (its last heartbeat, else when its last lease lapsed)."""
    driver: Driver | None
    """The driver heard from last, when the ledger knows it."""


@dataclass(frozen=True)
class Holders:
    """Why a driver can take nothing of a job now: other drivers hold every unfinished task."""

    tasks: int
    """Running tasks held under live leases by others."""
    live: list[Driver]
    """Drivers of this machine seen alive that hold some of them (they will finish them)."""
    unknown: list[str]
    """Holders whose liveness this machine cannot see (another machine, or no driver record):
    their leases decide."""
    until: float
    """When the last of those leases lapses unless renewed."""


@dataclass(frozen=True)
class Claim:
    """A task this owner may run now, under ``attempt_id``, until the lease expires."""

    task: Task
    attempt_id: str


class Ledger:
    """One ledger file; open one instance per process (connections are not shared)."""

    def __init__(self, path: str | Path, timeout: float = 30.0) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(str(self.path), timeout=timeout, isolation_level=None)
        except (OSError, sqlite3.Error) as exc:
            raise LedgerError(f"{self.path}: cannot open the job ledger ({exc}); check --home / DATAGEN_HOME") from None
        self._db.row_factory = sqlite3.Row
        self._db.execute(f"PRAGMA busy_timeout={int(timeout * 1000)}")
        self._retry_locked(lambda: self._db.execute("PRAGMA journal_mode=WAL"), timeout)
        self._db.execute("PRAGMA synchronous=NORMAL")

        def create_schema() -> None:
            with self._transaction() as db:
                counted = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'task_counts'")
                had_counts = counted.fetchone() is not None
                for statement in _SCHEMA.strip().split(";"):
                    if statement.strip():
                        db.execute(statement)
                for trigger in _TRIGGERS:
                    db.execute(trigger)
                if not had_counts:  # a ledger from before the counts: count its tasks once
                    db.execute(
                        "INSERT INTO task_counts (job_id, state, tasks, samples) SELECT job_id, state, COUNT(*), "
                        "COALESCE(SUM(samples), 0) FROM tasks GROUP BY job_id, state"
                    )

        self._retry_locked(create_schema, timeout)

    @staticmethod
    def _retry_locked(action: Callable[[], object], timeout: float) -> None:
        """Switching to WAL or creating the schema needs a lock that SQLite does not wait for when
        several processes open a new ledger at once; retry with a short back-off."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                action()
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def close(self) -> None:
        self._db.close()

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    # -- jobs ---------------------------------------------------------------------------------
    def create_job(
        self, job_id: str, spec: dict[str, Any], out: str, tasks: Iterable[tuple[str, dict[str, Any]]]
    ) -> Job:
        """Add a pending job with its tasks (in order; read once, as they come); idempotent for an
        existing job id. Each task's spec is a row of its own: keep them out of ``spec``."""
        now = time.time()
        with self._transaction() as db:
            exists = db.execute("SELECT 1 FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
            if not exists:
                db.execute(
                    "INSERT INTO jobs (job_id, state, spec, out, created, updated) VALUES (?, ?, ?, ?, ?, ?)",
                    (job_id, PENDING, json.dumps(spec, sort_keys=True), out, now, now),
                )
                db.executemany(
                    "INSERT INTO tasks (job_id, task_id, position, state, spec, updated) VALUES (?, ?, ?, ?, ?, ?)",
                    (
                        (job_id, task_id, position, PENDING, json.dumps(task_spec, sort_keys=True), now)
                        for position, (task_id, task_spec) in enumerate(tasks)
                    ),
                )
        return self.job(job_id)

    def job(self, job_id: str) -> Job:
        row = self._db.execute("SELECT * FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
        if row is None:
            raise LedgerError(f"no job {job_id!r} in {self.path}; 'datagen status' lists the jobs")
        return _job(row)

    def job_state(self, job_id: str) -> str:
        """The job's state alone (a driver looks at it every tick; the spec is not read)."""
        row = self._db.execute("SELECT state FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
        if row is None:
            raise LedgerError(f"no job {job_id!r} in {self.path}; 'datagen status' lists the jobs")
        return str(row["state"])

    def jobs(self) -> list[Job]:
        """Every job, oldest first."""
        return [_job(r) for r in self._db.execute("SELECT * FROM jobs ORDER BY created, job_id")]

    def runnable_jobs(self) -> list[Job]:
        """Jobs that may have work left (pending or running), oldest first. Several drivers may
        work on one job: task claims, not jobs, are exclusive."""
        rows = self._db.execute("SELECT * FROM jobs WHERE state IN (?, ?) ORDER BY created, job_id", (PENDING, RUNNING))
        return [_job(r) for r in rows]

    def start_job(
        self, job_id: str, owner: str, lease: float = DEFAULT_LEASE, process: ProcessIdentity | None = None
    ) -> Job:
        """Mark a pending or running job running and record ``owner`` as one of its drivers (this
        process unless ``process`` says otherwise), with a heartbeat valid for ``lease`` seconds."""
        process = process or process_identity()
        now = time.time()
        with self._transaction() as db:
            started = db.execute(
                "UPDATE jobs SET state = ?, owner = ?, updated = ? WHERE job_id = ? AND state IN (?, ?)",
                (RUNNING, owner, now, job_id, PENDING, RUNNING),
            ).rowcount
            if started:
                db.execute(
                    "INSERT OR REPLACE INTO drivers (driver_id, job_id, host, machine, pid, process_start, started, "
                    "heartbeat, lease) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (owner, job_id, process.host, process.machine, process.pid, process.start, now, now, lease),
                )
        return self.job(job_id)

    def leave(self, job_id: str, owner: str) -> None:
        """A driver stops working on a job: tasks it still holds become pending again, its record
        goes, and a running job no other live driver works on becomes pending (queued for anyone)."""
        now = time.time()
        with self._transaction() as db:
            db.execute(
                "UPDATE tasks SET state = ?, lease_owner = NULL, lease_expires = NULL, updated = ? "
                "WHERE job_id = ? AND lease_owner = ? AND state = ?",
                (PENDING, now, job_id, owner, RUNNING),
            )
            db.execute("DELETE FROM drivers WHERE driver_id = ?", (owner,))
            others = [_driver(r) for r in db.execute("SELECT * FROM drivers WHERE job_id = ?", (job_id,))]
            if not any(not d.lost(now) for d in others):
                db.execute(
                    "UPDATE jobs SET state = ?, owner = NULL, updated = ? WHERE job_id = ? AND state = ?",
                    (PENDING, now, job_id, RUNNING),
                )

    def drivers(self, job_id: str) -> list[Driver]:
        """The drivers recorded on a job (alive or lost), oldest first."""
        rows = self._db.execute("SELECT * FROM drivers WHERE job_id = ? ORDER BY started, driver_id", (job_id,))
        return [_driver(r) for r in rows]

    def lost_driver(self, job_id: str) -> LostDriver | None:
        """For a running job that no live driver works on (its drivers died, or every lease held on
        it lapsed): when it was last heard from. None for a job in any other state or still driven."""
        job = self.job(job_id)
        if job.state != RUNNING:
            return None
        now = time.time()
        drivers = self.drivers(job_id)
        if any(not d.lost(now) for d in drivers):
            return None
        known = {d.driver_id for d in drivers}
        running = self.tasks(job_id, (RUNNING,))
        if any(t.lease_owner not in known and (t.lease_expires or 0.0) >= now for t in running):
            return None  # a holder this ledger has no record of, under a live lease
        if drivers:
            last = max(drivers, key=lambda d: d.heartbeat)
            return LostDriver(since=last.heartbeat, driver=last)
        lapsed = [t.lease_expires for t in running if t.lease_expires is not None]
        return LostDriver(since=max(lapsed) if lapsed else job.updated, driver=None)

    def finish_job(self, job_id: str, summary: dict[str, Any], other_failures: int = 0) -> Job:
        """done when every task is done, failed when any failed (or ``other_failures``, such as
        objects-file lines that named no object); a cancelled job stays cancelled."""
        counts = self.task_counts(job_id)
        state = FAILED if counts.get(FAILED, 0) or other_failures else DONE
        if counts.get(PENDING, 0) or counts.get(RUNNING, 0):
            state = PENDING
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET state = ?, summary = ?, updated = ?, owner = NULL WHERE job_id = ? AND state != ?",
                (state, json.dumps(summary, sort_keys=True), time.time(), job_id, CANCELLED),
            )
        return self.job(job_id)

    def fail_job(self, job_id: str, message: str) -> Job:
        """A job that cannot run at all (its output is unusable, say): failed, with the reason.

        Not while another driver of this job is alive (a `resume` that cannot start beside a
        running driver, say): that driver runs it, and its outcome decides the job's state."""
        self.job(job_id)
        now = time.time()
        with self._transaction() as db:
            drivers = [_driver(r) for r in db.execute("SELECT * FROM drivers WHERE job_id = ?", (job_id,))]
            if any(not d.lost(now) for d in drivers):
                return self.job(job_id)
            db.execute(
                "UPDATE jobs SET state = ?, summary = ?, updated = ?, owner = NULL WHERE job_id = ?",
                (FAILED, json.dumps({"error": message}, sort_keys=True), time.time(), job_id),
            )
        return self.job(job_id)

    def cancel_job(self, job_id: str) -> Job:
        """Cancel a job and its unfinished tasks; finished tasks keep their state."""
        self.job(job_id)
        now = time.time()
        with self._transaction() as db:
            db.execute(
                "UPDATE jobs SET state = ?, updated = ? WHERE job_id = ? AND state NOT IN (?, ?)",
                (CANCELLED, now, job_id, DONE, FAILED),
            )
            db.execute(
                "UPDATE tasks SET state = ?, lease_owner = NULL, updated = ? WHERE job_id = ? AND state IN (?, ?)",
                (CANCELLED, now, job_id, PENDING, RUNNING),
            )
        return self.job(job_id)

    def reopen_job(self, job_id: str) -> Job:
        """For resume: tasks not done become pending again (attempt counts kept), except those a live
        driver still runs (its record says so); lost drivers' records go. A task held by an owner
        the ledger has no record of is taken back at once, whatever its lease says."""
        self.job(job_id)
        now = time.time()
        with self._transaction() as db:
            drivers = [_driver(r) for r in db.execute("SELECT * FROM drivers WHERE job_id = ?", (job_id,))]
            live = [d.driver_id for d in drivers if not d.lost(now)]
            for driver in drivers:
                if driver.driver_id not in live:
                    db.execute("DELETE FROM drivers WHERE driver_id = ?", (driver.driver_id,))
            marks = ", ".join("?" for _ in live)
            held_by_live = f" AND NOT (state = ? AND lease_owner IN ({marks}))" if live else ""
            db.execute(  # every state but done, named so that the index skips the done tasks
                "UPDATE tasks SET state = ?, lease_owner = NULL, lease_expires = NULL, updated = ? "
                f"WHERE job_id = ? AND state IN (?, ?, ?, ?){held_by_live}",
                (PENDING, now, job_id, PENDING, RUNNING, FAILED, CANCELLED, *([RUNNING, *live] if live else [])),
            )
            db.execute(
                "UPDATE jobs SET state = ?, updated = ? WHERE job_id = ? AND NOT (state = ? AND ?)",
                (PENDING, now, job_id, RUNNING, bool(live)),
            )
        return self.job(job_id)

    def redo_tasks(self, job_id: str, task_ids: Sequence[str]) -> Job:
        """For `datagen shards repair`: these finished tasks (their shards were found damaged and
        their commit records withdrawn) become pending again, and so does the job, so a driver runs
        exactly them. Refused while a live driver holds the job (it may still be writing)."""
        job = self.job(job_id)
        now = time.time()
        with self._transaction() as db:
            drivers = [_driver(r) for r in db.execute("SELECT * FROM drivers WHERE job_id = ?", (job_id,))]
            if job.state == RUNNING and any(not d.lost(now) for d in drivers):
                raise LedgerError(f"job {job_id} is running; wait for it to finish (or cancel it), then repair")
            marks = ", ".join("?" for _ in task_ids)
            db.execute(
                "UPDATE tasks SET state = ?, lease_owner = NULL, lease_expires = NULL, error = NULL, updated = ? "
                f"WHERE job_id = ? AND task_id IN ({marks})",
                (PENDING, now, job_id, *task_ids),
            )
            db.execute("UPDATE jobs SET state = ?, updated = ? WHERE job_id = ?", (PENDING, now, job_id))
        return self.job(job_id)

    # -- tasks --------------------------------------------------------------------------------
    def tasks(self, job_id: str, states: Sequence[str] | None = None) -> list[Task]:
        """The job's tasks in order (only those in ``states``, when given: read from the index)."""
        return list(self.each_task(job_id, states))

    def each_task(self, job_id: str, states: Sequence[str] | None = None) -> Iterator[Task]:
        """`tasks`, one at a time (a listing of 100,000 tasks need not be held at once)."""
        if states is None:
            rows = self._db.execute("SELECT * FROM tasks WHERE job_id = ? ORDER BY position", (job_id,))
        else:
            marks = ", ".join("?" for _ in states)
            rows = self._db.execute(
                f"SELECT * FROM tasks WHERE job_id = ? AND state IN ({marks}) ORDER BY position", (job_id, *states)
            )
        for row in rows:
            yield _task(row)

    def task_ids(self, job_id: str) -> list[str]:
        """The job's task ids in order."""
        rows = self._db.execute("SELECT task_id FROM tasks WHERE job_id = ? ORDER BY position", (job_id,))
        return [str(row["task_id"]) for row in rows]

    def task(self, job_id: str, task_id: str) -> Task:
        row = self._db.execute("SELECT * FROM tasks WHERE job_id = ? AND task_id = ?", (job_id, task_id)).fetchone()
        if row is None:
            raise LedgerError(f"no task {task_id!r} in job {job_id!r}")
        return _task(row)

    def task_counts(self, job_id: str) -> dict[str, int]:
        """Tasks per state (states with none left out), from the counts the triggers keep."""
        rows = self._db.execute(
            "SELECT state, tasks FROM task_counts WHERE job_id = ? AND tasks > 0 ORDER BY state", (job_id,)
        )
        return {r["state"]: int(r["tasks"]) for r in rows}

    def claim(self, job_id: str, owner: str, lease: float, limit: int = 1) -> list[Claim]:
        """Up to ``limit`` runnable tasks (pending, running with an expired lease, or running under
        a lost driver), in order, each with a fresh attempt id and a lease for ``owner``."""
        now = time.time()
        claims: list[Claim] = []
        with self._transaction() as db:
            job = db.execute("SELECT state FROM jobs WHERE job_id = ?", (job_id,)).fetchone()
            if job is None or job["state"] in (CANCELLED, DONE, FAILED):
                return []
            pending = db.execute(
                "SELECT * FROM tasks WHERE job_id = ? AND state = ? ORDER BY position LIMIT ?", (job_id, PENDING, limit)
            ).fetchall()
            condition, params = self._reclaimable(db, job_id, now)
            stale = db.execute(
                f"SELECT * FROM tasks WHERE job_id = ? AND state = ? AND {condition} ORDER BY position LIMIT ?",
                (job_id, RUNNING, *params, limit),
            ).fetchall()
            for row in sorted([*pending, *stale], key=lambda r: int(r["position"]))[:limit]:
                attempt_id = f"a{int(row['attempts']) + 1}-{uuid.uuid4().hex[:12]}"
                db.execute(
                    "UPDATE tasks SET state = ?, attempts = attempts + 1, attempt_id = ?, lease_owner = ?, "
                    "lease_expires = ?, updated = ? WHERE job_id = ? AND task_id = ?",
                    (RUNNING, attempt_id, owner, now + lease, now, job_id, row["task_id"]),
                )
                updated = db.execute(
                    "SELECT * FROM tasks WHERE job_id = ? AND task_id = ?", (job_id, row["task_id"])
                ).fetchone()
                claims.append(Claim(task=_task(updated), attempt_id=attempt_id))
        return claims

    def claimable(self, job_id: str) -> int:
        """How many tasks `claim` would hand out now (ignoring the job's state)."""
        condition, params = self._reclaimable(self._db, job_id, time.time())
        query = f"SELECT COUNT(*) AS n FROM tasks WHERE job_id = ? AND state = ? AND {condition}"
        row = self._db.execute(query, (job_id, RUNNING, *params))
        return self.task_counts(job_id).get(PENDING, 0) + int(row.fetchone()["n"])

    def holders(self, job_id: str) -> Holders | None:
        """Who holds a job's unfinished tasks when a driver can claim none of them (None when some
        task is claimable, or none is running)."""
        if self.claimable(job_id):
            return None
        now = time.time()
        running = self.tasks(job_id, (RUNNING,))
        if not running:
            return None
        drivers = {d.driver_id: d for d in self.drivers(job_id)}
        live: dict[str, Driver] = {}
        unknown: dict[str, float] = {}
        for task in running:
            owner = task.lease_owner or "?"
            driver = drivers.get(owner)
            if driver is not None and process_alive(driver.process):
                live[owner] = driver
            else:
                unknown[owner] = max(unknown.get(owner, 0.0), task.lease_expires or now)
        return Holders(
            tasks=len(running),
            live=list(live.values()),
            unknown=sorted(unknown),
            until=max(unknown.values(), default=now),
        )

    def _reclaimable(self, db: sqlite3.Connection, job_id: str, now: float) -> tuple[str, list[Any]]:
        """The SQL condition (and its parameters) of a *running* task that may be claimed now: its
        lease expired, or its driver is known to be lost. With the pending tasks, these are what
        `claim` hands out; each is read from the index's range of running tasks alone."""
        rows = db.execute(
            "SELECT DISTINCT d.* FROM tasks t JOIN drivers d ON d.driver_id = t.lease_owner "
            "WHERE t.job_id = ? AND t.state = ? AND t.lease_expires >= ?",
            (job_id, RUNNING, now),
        )
        lost = [driver.driver_id for driver in (_driver(r) for r in rows) if driver.lost(now)]
        condition = "(lease_expires < ?"
        params: list[Any] = [now]
        if lost:
            condition += f" OR lease_owner IN ({', '.join('?' for _ in lost)})"
            params += lost
        return condition + ")", params

    def renew(self, job_id: str, owner: str, lease: float) -> None:
        """Extend every lease this owner holds in a job, and its heartbeat (called periodically by a
        live driver)."""
        now = time.time()
        with self._transaction() as db:
            db.execute(
                "UPDATE tasks SET lease_expires = ? WHERE job_id = ? AND lease_owner = ? AND state = ?",
                (now + lease, job_id, owner, RUNNING),
            )
            db.execute("UPDATE drivers SET heartbeat = ?, lease = ? WHERE driver_id = ?", (now, lease, owner))

    def done_samples(self, job_id: str) -> int:
        """Samples of the job's done tasks, whoever ran them (from the counts the triggers keep)."""
        row = self._db.execute(
            "SELECT samples FROM task_counts WHERE job_id = ? AND state = ?", (job_id, DONE)
        ).fetchone()
        return int(row["samples"]) if row is not None else 0

    def release(self, job_id: str, task_id: str, attempt_id: str) -> bool:
        """Give a claimed task back (pending again), e.g. when its worker was lost."""
        return self._transition(job_id, task_id, attempt_id, PENDING, {"lease_owner": None})

    def complete(self, job_id: str, task_id: str, attempt_id: str, samples: int, placement: str | None) -> bool:
        """Mark done. Accepted from the current attempt, or from any attempt once the task is
        committed by another (the dataset's commit record decides which attempt readers follow)."""
        return self._transition(
            job_id,
            task_id,
            attempt_id,
            DONE,
            {"samples": samples, "placement": placement, "error": None},
            any_attempt=True,
        )

    def fail(self, job_id: str, task_id: str, attempt_id: str, error: str) -> bool:
        return self._transition(job_id, task_id, attempt_id, FAILED, {"error": error})

    def _transition(
        self,
        job_id: str,
        task_id: str,
        attempt_id: str,
        state: str,
        fields: dict[str, Any],
        any_attempt: bool = False,
    ) -> bool:
        assignments = ", ".join(f"{name} = ?" for name in ("state", "updated", *fields))
        condition = "job_id = ? AND task_id = ? AND state NOT IN (?, ?)"
        params: list[Any] = [state, time.time(), *fields.values(), job_id, task_id, DONE, CANCELLED]
        if not any_attempt:
            condition += " AND attempt_id = ?"
            params.append(attempt_id)
        with self._transaction() as db:
            changed = db.execute(f"UPDATE tasks SET {assignments} WHERE {condition}", params).rowcount
        return bool(changed)


def _job(row: sqlite3.Row) -> Job:
    return Job(
        job_id=row["job_id"],
        state=row["state"],
        spec=json.loads(row["spec"]),
        out=row["out"],
        created=row["created"],
        updated=row["updated"],
        owner=row["owner"],
        summary=json.loads(row["summary"]) if row["summary"] else None,
    )


def _driver(row: sqlite3.Row) -> Driver:
    return Driver(
        driver_id=row["driver_id"],
        job_id=row["job_id"],
        process=ProcessIdentity(host=row["host"], machine=row["machine"], pid=row["pid"], start=row["process_start"]),
        started=row["started"],
        heartbeat=row["heartbeat"],
        lease=row["lease"],
    )


def _task(row: sqlite3.Row) -> Task:
    return Task(
        job_id=row["job_id"],
        task_id=row["task_id"],
        position=row["position"],
        state=row["state"],
        spec_text=row["spec"],
        attempts=row["attempts"],
        attempt_id=row["attempt_id"],
        lease_owner=row["lease_owner"],
        lease_expires=row["lease_expires"],
        error=row["error"],
        placement=row["placement"],
        samples=row["samples"],
    )
