"""The ledger's answers that must stay cheap at 100,000 tasks, checked for being right (no Ray):
the task counts and done samples the triggers keep equal a recount of the rows after every kind
of transition, by any path and from several processes; a ledger made before the counts gets them
counted once when opened; claims take pending tasks and lapsed or lost leases together in position
order; a job's state is read alone; a task's spec is parsed only when asked for."""

from __future__ import annotations

import json
import multiprocessing
import random
import sqlite3
import time
from pathlib import Path

import pytest

from jobs.ledger import CANCELLED, DONE, FAILED, PENDING, RUNNING, Ledger

JOB = "job-1"


def task_list(count: int, prefix: str = "t") -> list[tuple[str, dict]]:
    return [(f"{prefix}{i:04d}", {"n": i}) for i in range(count)]


@pytest.fixture
def ledger(tmp_path: Path):
    led = Ledger(tmp_path / "ledger.db")
    yield led
    led.close()


def recount(path: Path, job_id: str = JOB) -> tuple[dict[str, int], int]:
    """Tasks per state and the done tasks' samples, counted from the rows themselves."""
    with sqlite3.connect(path) as db:
        counts = dict(db.execute("SELECT state, COUNT(*) FROM tasks WHERE job_id = ? GROUP BY state", (job_id,)))
        (samples,) = db.execute(
            "SELECT COALESCE(SUM(samples), 0) FROM tasks WHERE job_id = ? AND state = ?", (job_id, DONE)
        ).fetchone()
    return counts, samples


def assert_counts_hold(ledger: Ledger, job_id: str = JOB) -> dict[str, int]:
    counts, samples = recount(ledger.path, job_id)
    assert ledger.task_counts(job_id) == counts
    assert ledger.done_samples(job_id) == samples
    return counts


def test_counts_follow_every_transition(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(12))
    assert assert_counts_hold(ledger) == {PENDING: 12}
    ledger.start_job(JOB, "A", lease=60)
    claims = ledger.claim(JOB, "A", 60, limit=8)
    assert assert_counts_hold(ledger) == {PENDING: 4, RUNNING: 8}
    for number, claim in enumerate(claims[:3]):
        assert ledger.complete(JOB, claim.task.task_id, claim.attempt_id, 10 + number, "node")
    assert not ledger.complete(JOB, claims[0].task.task_id, claims[0].attempt_id, 99, "node")  # idempotent
    assert ledger.fail(JOB, claims[3].task.task_id, claims[3].attempt_id, "bad mesh")
    assert ledger.release(JOB, claims[4].task.task_id, claims[4].attempt_id)
    assert assert_counts_hold(ledger) == {DONE: 3, FAILED: 1, PENDING: 5, RUNNING: 3}
    assert ledger.done_samples(JOB) == 10 + 11 + 12
    ledger.renew(JOB, "A", 60)  # leases only: no count moves
    ledger.leave(JOB, "A")
    assert assert_counts_hold(ledger) == {DONE: 3, FAILED: 1, PENDING: 8}
    ledger.cancel_job(JOB)
    assert assert_counts_hold(ledger) == {DONE: 3, FAILED: 1, CANCELLED: 8}
    ledger.reopen_job(JOB)
    assert assert_counts_hold(ledger) == {DONE: 3, PENDING: 9}
    done = sorted(t.task_id for t in ledger.tasks(JOB, (DONE,)))
    ledger.redo_tasks(JOB, done[:2])
    assert assert_counts_hold(ledger) == {DONE: 1, PENDING: 11}
    assert ledger.done_samples(JOB) == 12  # the redone tasks' samples left the done count
    for claim in ledger.claim(JOB, "B", 60, limit=100):
        ledger.complete(JOB, claim.task.task_id, claim.attempt_id, 1, None)
    assert assert_counts_hold(ledger) == {DONE: 12}
    assert ledger.finish_job(JOB, {}).state == DONE


def test_counts_are_per_job(ledger: Ledger) -> None:
    ledger.create_job("a", {}, "/a", task_list(3))
    ledger.create_job("b", {}, "/b", task_list(5, prefix="u"))
    (claim,) = ledger.claim("b", "A", 60)
    ledger.complete("b", claim.task.task_id, claim.attempt_id, 7, None)
    assert ledger.task_counts("a") == {PENDING: 3} and ledger.done_samples("a") == 0
    assert ledger.task_counts("b") == {DONE: 1, PENDING: 4} and ledger.done_samples("b") == 7
    assert ledger.task_counts("unknown") == {} and ledger.done_samples("unknown") == 0


def test_counts_follow_random_transitions_by_any_path(ledger: Ledger) -> None:
    """Seeded random walks over the ledger's calls, plus a change made in SQL behind its back: the
    counts equal a recount after each step."""
    rng = random.Random(40)
    ledger.create_job(JOB, {}, "/out", task_list(30))
    ledger.start_job(JOB, "A", lease=60)
    held = []
    for _ in range(150):
        action = rng.choice(["claim", "complete", "fail", "release", "cancel", "reopen", "raw"])
        if action == "claim":
            held += ledger.claim(JOB, rng.choice(["A", "B"]), 60, limit=rng.randint(1, 4))
        elif action in ("complete", "fail", "release") and held:
            claim = held.pop(rng.randrange(len(held)))
            task_id, attempt = claim.task.task_id, claim.attempt_id
            if action == "complete":
                ledger.complete(JOB, task_id, attempt, rng.randint(0, 9), None)
            elif action == "fail":
                ledger.fail(JOB, task_id, attempt, "x")
            else:
                ledger.release(JOB, task_id, attempt)
        elif action == "cancel" and rng.random() < 0.2:
            ledger.cancel_job(JOB)
        elif action == "reopen":
            ledger.reopen_job(JOB)
        elif action == "raw":
            with sqlite3.connect(ledger.path) as db:
                changed = (rng.randint(0, 5), JOB, 3)
                db.execute("UPDATE tasks SET samples = ? WHERE job_id = ? AND position = ?", changed)
        assert_counts_hold(ledger)


def _claim_and_complete(path: str, owner: str) -> None:
    ledger = Ledger(path)
    try:
        while claims := ledger.claim(JOB, owner, 60, limit=3):
            for claim in claims:
                ledger.complete(JOB, claim.task.task_id, claim.attempt_id, 2, owner)
    finally:
        ledger.close()


def test_counts_hold_with_several_processes_claiming(tmp_path: Path) -> None:
    path = tmp_path / "ledger.db"
    ledger = Ledger(path)
    ledger.create_job(JOB, {}, "/out", task_list(120))
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_claim_and_complete, args=(str(path), f"p{i}")) for i in range(3)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(timeout=120)
        assert worker.exitcode == 0
    assert assert_counts_hold(ledger) == {DONE: 120}
    assert ledger.done_samples(JOB) == 240
    ledger.close()


OLD_SCHEMA = """
CREATE TABLE jobs (job_id TEXT PRIMARY KEY, state TEXT NOT NULL, spec TEXT NOT NULL, out TEXT NOT NULL,
    created REAL NOT NULL, updated REAL NOT NULL, owner TEXT, summary TEXT);
CREATE TABLE tasks (job_id TEXT NOT NULL, task_id TEXT NOT NULL, position INTEGER NOT NULL, state TEXT NOT NULL,
    spec TEXT NOT NULL, attempts INTEGER NOT NULL DEFAULT 0, attempt_id TEXT, lease_owner TEXT, lease_expires REAL,
    error TEXT, placement TEXT, samples INTEGER, updated REAL NOT NULL, PRIMARY KEY (job_id, task_id));
CREATE INDEX tasks_by_state ON tasks (job_id, state, position);
"""


def test_a_ledger_from_before_the_counts_is_counted_once_when_opened(tmp_path: Path) -> None:
    """A ledger written by the code before the counts existed (its job spec holding every task, as it
    did then) opens with its counts right, and keeps them right from then on."""
    path = tmp_path / "ledger.db"
    now = time.time()
    states = [DONE, DONE, FAILED, PENDING, RUNNING, CANCELLED, PENDING]
    with sqlite3.connect(path) as db:
        db.executescript(OLD_SCHEMA)
        spec = {"tasks": [{"task_id": f"t{i}"} for i in range(len(states))], "config": {}}
        job = (JOB, PENDING, json.dumps(spec), "/o", now, now)
        db.execute("INSERT INTO jobs VALUES (?, ?, ?, ?, ?, ?, NULL, NULL)", job)
        db.executemany(
            "INSERT INTO tasks (job_id, task_id, position, state, spec, samples, updated) VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(JOB, f"t{i}", i, state, "{}", 5 if state == DONE else None, now) for i, state in enumerate(states)],
        )
    ledger = Ledger(path)
    assert assert_counts_hold(ledger) == {DONE: 2, FAILED: 1, PENDING: 2, RUNNING: 1, CANCELLED: 1}
    assert ledger.done_samples(JOB) == 10
    ledger.reopen_job(JOB)
    assert assert_counts_hold(ledger) == {DONE: 2, PENDING: 5}
    ledger.close()
    again = Ledger(path)  # opened again: counted once, not twice
    assert assert_counts_hold(again) == {DONE: 2, PENDING: 5}
    again.close()


def test_claim_takes_pending_and_reclaimable_tasks_together_in_order(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(8))
    live = ledger.claim(JOB, "live", lease=600, limit=2)  # t0000-t0001
    lapsed = ledger.claim(JOB, "old", lease=-1, limit=3)  # t0002-t0004, leases already lapsed
    assert [c.task.task_id for c in live + lapsed] == ["t0000", "t0001", "t0002", "t0003", "t0004"]
    assert ledger.claimable(JOB) == 3 + 3  # three pending, three lapsed
    taken = ledger.claim(JOB, "new", 600, limit=4)
    assert [c.task.task_id for c in taken] == ["t0002", "t0003", "t0004", "t0005"]
    assert [c.task.attempts for c in taken] == [2, 2, 2, 1]
    assert ledger.claimable(JOB) == 2
    rest = ledger.claim(JOB, "new", 600, limit=10)
    assert [c.task.task_id for c in rest] == ["t0006", "t0007"]
    assert ledger.claim(JOB, "new", 600, limit=10) == [] and ledger.claimable(JOB) == 0


def test_job_state_and_task_specs_on_demand(ledger: Ledger) -> None:
    ledger.create_job(JOB, {"config": {"a": 1}}, "/out", [("t1", {"b": [1, 2]}), ("t2", {"b": []})])
    assert ledger.job_state(JOB) == PENDING
    ledger.cancel_job(JOB)
    assert ledger.job_state(JOB) == CANCELLED
    first, second = ledger.tasks(JOB)
    assert json.loads(first.spec_text) == {"b": [1, 2]} and first.spec == {"b": [1, 2]} and second.spec == {"b": []}
    assert "spec_text" not in repr(first)
    assert ledger.task_ids(JOB) == ["t1", "t2"]
    assert [t.task_id for t in ledger.each_task(JOB, (CANCELLED,))] == ["t1", "t2"]
    assert ledger.tasks(JOB, (DONE, PENDING)) == []
