"""The job ledger (jobs/ledger.py), no Ray: state transitions, idempotence, leases that expire,
stale attempts, cancel and reopen, several processes claiming from one ledger file, and the
liveness of drivers (jobs/liveness.py): a dead driver of this machine is noticed at once, one
elsewhere when its heartbeat is older than its lease."""

from __future__ import annotations

import multiprocessing
import random
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from jobs.ledger import CANCELLED, DONE, FAILED, PENDING, RUNNING, Ledger, LedgerError
from jobs.liveness import ProcessIdentity, process_alive, process_identity

JOB = "job-1"


def task_list(count: int, prefix: str = "t") -> list[tuple[str, dict]]:
    return [(f"{prefix}{i:04d}", {"n": i}) for i in range(count)]


@pytest.fixture
def ledger(tmp_path: Path):
    led = Ledger(tmp_path / "ledger.db")
    yield led
    led.close()


def states(ledger: Ledger, job_id: str = JOB) -> dict[str, str]:
    return {t.task_id: t.state for t in ledger.tasks(job_id)}


# ---------------------------------------------------------------------------------------------------------
# jobs
# ---------------------------------------------------------------------------------------------------------


def test_create_job_is_pending_with_ordered_pending_tasks(ledger: Ledger) -> None:
    job = ledger.create_job(JOB, {"config": {"a": 1}}, "/out", task_list(3))
    assert job.state == PENDING and job.out == "/out" and job.spec == {"config": {"a": 1}}
    assert job.summary is None and job.owner is None
    tasks = ledger.tasks(JOB)
    assert [t.task_id for t in tasks] == ["t0000", "t0001", "t0002"]
    assert [t.position for t in tasks] == [0, 1, 2]
    assert all(t.state == PENDING and t.attempts == 0 and t.attempt_id is None for t in tasks)
    assert tasks[1].spec == {"n": 1}
    assert ledger.task_counts(JOB) == {PENDING: 3}


def test_create_job_twice_keeps_the_first(ledger: Ledger) -> None:
    ledger.create_job(JOB, {"v": 1}, "/out", task_list(3))
    (claim,) = ledger.claim(JOB, "A", 60)
    again = ledger.create_job(JOB, {"v": 2}, "/other", task_list(5, prefix="u"))
    assert again.spec == {"v": 1} and again.out == "/out"
    assert [t.task_id for t in ledger.tasks(JOB)] == ["t0000", "t0001", "t0002"]
    assert ledger.task(JOB, claim.task.task_id).state == RUNNING


def test_unknown_job_and_task_raise_ledger_error(ledger: Ledger) -> None:
    for call in (
        lambda: ledger.job("nope"),
        lambda: ledger.cancel_job("nope"),
        lambda: ledger.reopen_job("nope"),
        lambda: ledger.task("nope", "t"),
    ):
        with pytest.raises(LedgerError, match="nope"):
            call()
    assert ledger.claim("nope", "A", 60) == []


def test_unopenable_ledger_path_is_a_ledger_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(LedgerError, match="--home"):
        Ledger(blocker / "ledger.db")


def test_runnable_jobs_are_pending_or_running_oldest_first(ledger: Ledger) -> None:
    for name in ("j1", "j2", "j3", "j4"):
        ledger.create_job(name, {}, "/out", task_list(1))
        time.sleep(0.002)
    ledger.start_job("j2", "A")
    ledger.cancel_job("j3")
    (claim,) = ledger.claim("j4", "A", 60)
    ledger.complete("j4", claim.task.task_id, claim.attempt_id, 1, None)
    ledger.finish_job("j4", {"ok": True})
    assert ledger.job("j4").state == DONE
    assert [j.job_id for j in ledger.runnable_jobs()] == ["j1", "j2"]
    assert [j.job_id for j in ledger.jobs()] == ["j1", "j2", "j3", "j4"]


# ---------------------------------------------------------------------------------------------------------
# claims and transitions
# ---------------------------------------------------------------------------------------------------------


def test_claim_in_order_up_to_limit_with_fresh_attempts(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(5))
    first = ledger.claim(JOB, "A", 60, limit=2)
    assert [c.task.task_id for c in first] == ["t0000", "t0001"]
    second = ledger.claim(JOB, "B", 60, limit=10)
    assert [c.task.task_id for c in second] == ["t0002", "t0003", "t0004"]
    assert ledger.claim(JOB, "C", 60, limit=10) == []
    attempt_ids = [c.attempt_id for c in first + second]
    assert len(set(attempt_ids)) == 5 and all(a.startswith("a1-") for a in attempt_ids)
    for claim in first:
        task = ledger.task(JOB, claim.task.task_id)
        assert (task.state, task.attempts, task.attempt_id, task.lease_owner) == (RUNNING, 1, claim.attempt_id, "A")
        assert task.lease_expires is not None and task.lease_expires > time.time() + 50
    assert ledger.task_counts(JOB) == {RUNNING: 5}


def test_complete_records_samples_and_is_idempotent(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    (claim,) = ledger.claim(JOB, "A", 60)
    assert ledger.complete(JOB, "t0000", claim.attempt_id, 7, "node@host")
    task = ledger.task(JOB, "t0000")
    assert (task.state, task.samples, task.placement, task.error) == (DONE, 7, "node@host", None)
    # twice is harmless: refused, nothing changes
    assert not ledger.complete(JOB, "t0000", claim.attempt_id, 99, "other")
    assert ledger.task(JOB, "t0000") == task
    # a done task can neither fail nor be released, nor be claimed again
    assert not ledger.fail(JOB, "t0000", claim.attempt_id, "late error")
    assert not ledger.release(JOB, "t0000", claim.attempt_id)
    assert ledger.claim(JOB, "B", 60) == []
    assert ledger.task(JOB, "t0000") == task


def test_fail_records_the_error_and_release_gives_the_task_back(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(2))
    c0, c1 = ledger.claim(JOB, "A", 60, limit=2)
    assert ledger.fail(JOB, "t0000", c0.attempt_id, "mesh has no faces")
    assert ledger.task(JOB, "t0000").state == FAILED
    assert ledger.task(JOB, "t0000").error == "mesh has no faces"
    assert ledger.release(JOB, "t0001", c1.attempt_id)
    released = ledger.task(JOB, "t0001")
    assert released.state == PENDING and released.lease_owner is None and released.attempts == 1
    (again,) = ledger.claim(JOB, "B", 60)
    assert again.task.task_id == "t0001" and again.attempt_id.startswith("a2-")
    assert ledger.task(JOB, "t0001").attempts == 2
    # a failed task is not claimed again (only reopen makes it pending)
    assert ledger.claim(JOB, "C", 60) == []


def test_wrong_attempt_cannot_fail_or_release(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    (claim,) = ledger.claim(JOB, "A", 60)
    assert not ledger.fail(JOB, "t0000", "a9-bogus", "x")
    assert not ledger.release(JOB, "t0000", "a9-bogus")
    task = ledger.task(JOB, "t0000")
    assert (task.state, task.attempt_id, task.error) == (RUNNING, claim.attempt_id, None)


def test_lease_expires_and_another_owner_claims_with_a_new_attempt(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    (old,) = ledger.claim(JOB, "A", 0.1)
    assert ledger.claim(JOB, "B", 60) == []  # lease still held
    time.sleep(0.25)
    (new,) = ledger.claim(JOB, "B", 60)
    assert new.task.task_id == "t0000"
    assert new.attempt_id != old.attempt_id and new.attempt_id.startswith("a2-")
    task = ledger.task(JOB, "t0000")
    assert (task.state, task.attempts, task.attempt_id, task.lease_owner) == (RUNNING, 2, new.attempt_id, "B")
    # the stale attempt cannot fail or release the re-claimed task...
    assert not ledger.fail(JOB, "t0000", old.attempt_id, "stale failure")
    assert not ledger.release(JOB, "t0000", old.attempt_id)
    assert ledger.task(JOB, "t0000") == task
    # ...but may complete it (its shard is as good: the dataset's commit record decides)
    assert ledger.complete(JOB, "t0000", old.attempt_id, 3, "old@host")
    assert ledger.task(JOB, "t0000").state == DONE
    # and then the newer attempt's report changes nothing
    assert not ledger.fail(JOB, "t0000", new.attempt_id, "too late")
    assert not ledger.complete(JOB, "t0000", new.attempt_id, 4, "new@host")
    done = ledger.task(JOB, "t0000")
    assert (done.state, done.samples, done.placement, done.attempts) == (DONE, 3, "old@host", 2)


def test_renew_extends_only_the_owners_leases(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(2))
    ledger.claim(JOB, "A", 0.2)
    ledger.claim(JOB, "B", 0.2)
    ledger.renew(JOB, "A", 60)
    time.sleep(0.35)
    claims = ledger.claim(JOB, "C", 60, limit=2)
    assert [c.task.task_id for c in claims] == ["t0001"]  # B's expired, A's renewed
    assert ledger.task(JOB, "t0000").lease_owner == "A"


def test_start_job_marks_running_with_owner(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    job = ledger.start_job(JOB, "driver-1")
    assert (job.state, job.owner) == (RUNNING, "driver-1")
    ledger.cancel_job(JOB)
    assert ledger.start_job(JOB, "driver-2").state == CANCELLED  # a cancelled job is not restarted


# ---------------------------------------------------------------------------------------------------------
# cancel, reopen, finish
# ---------------------------------------------------------------------------------------------------------


def _mixed_job(ledger: Ledger) -> dict[str, str]:
    """t0: done, t1: failed, t2: running, t3: pending. Returns task id -> last attempt id."""
    ledger.create_job(JOB, {}, "/out", task_list(4))
    c0, c1, c2 = ledger.claim(JOB, "A", 60, limit=3)
    ledger.complete(JOB, "t0000", c0.attempt_id, 5, "p")
    ledger.fail(JOB, "t0001", c1.attempt_id, "bad mesh")
    return {"t0000": c0.attempt_id, "t0001": c1.attempt_id, "t0002": c2.attempt_id}


def test_cancel_keeps_finished_tasks_and_stops_claims(ledger: Ledger) -> None:
    attempts = _mixed_job(ledger)
    job = ledger.cancel_job(JOB)
    assert job.state == CANCELLED
    assert states(ledger) == {"t0000": DONE, "t0001": FAILED, "t0002": CANCELLED, "t0003": CANCELLED}
    assert ledger.task(JOB, "t0000").samples == 5
    assert ledger.task(JOB, "t0002").lease_owner is None
    assert ledger.claim(JOB, "B", 60) == []
    # the running attempt's late failure does not overwrite the cancellation
    assert not ledger.fail(JOB, "t0002", attempts["t0002"], "killed")
    assert ledger.task(JOB, "t0002").state == CANCELLED
    # cancel is idempotent, and finishing a cancelled job leaves it cancelled
    assert ledger.cancel_job(JOB).state == CANCELLED
    assert ledger.finish_job(JOB, {"x": 1}).state == CANCELLED
    assert not ledger.runnable_jobs()


def test_cancel_does_not_touch_a_finished_job(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    (claim,) = ledger.claim(JOB, "A", 60)
    ledger.complete(JOB, "t0000", claim.attempt_id, 1, None)
    ledger.finish_job(JOB, {})
    assert ledger.cancel_job(JOB).state == DONE
    assert states(ledger) == {"t0000": DONE}


def test_reopen_makes_unfinished_tasks_pending_and_keeps_attempts(ledger: Ledger) -> None:
    _mixed_job(ledger)
    ledger.cancel_job(JOB)
    job = ledger.reopen_job(JOB)
    assert job.state == PENDING
    assert states(ledger) == {"t0000": DONE, "t0001": PENDING, "t0002": PENDING, "t0003": PENDING}
    tasks = {t.task_id: t for t in ledger.tasks(JOB)}
    assert [tasks[t].attempts for t in sorted(tasks)] == [1, 1, 1, 0]
    assert tasks["t0002"].lease_owner is None and tasks["t0002"].lease_expires is None
    claims = ledger.claim(JOB, "B", 60, limit=10)
    assert [c.task.task_id for c in claims] == ["t0001", "t0002", "t0003"]
    assert [c.attempt_id[:3] for c in claims] == ["a2-", "a2-", "a1-"]
    assert ledger.task(JOB, "t0000").attempts == 1  # done task untouched


def test_reopen_takes_back_a_dead_drivers_running_tasks_at_once(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(2))
    ledger.claim(JOB, "dead-driver", 3600, limit=2)
    assert ledger.claim(JOB, "B", 60) == []  # the leases would hold for an hour
    ledger.reopen_job(JOB)
    claims = ledger.claim(JOB, "B", 60, limit=2)
    assert [c.task.task_id for c in claims] == ["t0000", "t0001"]
    assert all(ledger.task(JOB, c.task.task_id).attempts == 2 for c in claims)


def test_finish_job_states(ledger: Ledger) -> None:
    for name, outcome in (("ok", "done"), ("bad", "fail"), ("lines", "done"), ("open", None)):
        ledger.create_job(name, {}, "/out", task_list(2))
        claims = ledger.claim(name, "A", 60, limit=2)
        for claim in claims if outcome else claims[:1]:
            if outcome == "fail" and claim is claims[0]:
                ledger.fail(name, claim.task.task_id, claim.attempt_id, "x")
            else:
                ledger.complete(name, claim.task.task_id, claim.attempt_id, 1, None)
    assert ledger.finish_job("ok", {"samples": 2}).state == DONE
    assert ledger.job("ok").summary == {"samples": 2} and ledger.job("ok").owner is None
    assert ledger.finish_job("bad", {}).state == FAILED
    assert ledger.finish_job("lines", {}, other_failures=1).state == FAILED
    assert ledger.finish_job("open", {}).state == PENDING  # a task still running: not finished


# ---------------------------------------------------------------------------------------------------------
# liveness: who drives a job, and whether it still runs
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture
def other_process() -> Iterator[subprocess.Popen]:
    """A live process of this machine to stand for another driver (killed by the test or after it)."""
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    yield process
    if process.poll() is None:
        process.kill()
        process.wait(timeout=30)


def far_driver(pid: int = 4242) -> ProcessIdentity:
    """A driver on another machine: its PID means nothing here."""
    return ProcessIdentity(host="far-host", machine="another-machine", pid=pid, start="1")


def test_process_identity_and_liveness(other_process: subprocess.Popen) -> None:
    me = process_identity()
    assert me.pid > 0 and me.host
    assert process_alive(me) is True
    other = process_identity(other_process.pid)
    assert process_alive(other) is True
    assert process_alive(far_driver()) is None  # elsewhere: only the heartbeat can tell
    if sys.platform.startswith("linux"):
        assert other.start  # the start time guards against a reused PID
        assert process_alive(ProcessIdentity(other.host, other.machine, other.pid, "1")) is False
    other_process.kill()
    other_process.wait(timeout=30)
    assert process_alive(other) is False


def test_start_job_records_the_driver_and_renew_its_heartbeat(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    ledger.start_job(JOB, "driver-1", lease=30)
    (driver,) = ledger.drivers(JOB)
    assert (driver.driver_id, driver.job_id, driver.lease) == ("driver-1", JOB, 30)
    assert driver.process == process_identity()
    assert not driver.lost()
    time.sleep(0.05)
    ledger.renew(JOB, "driver-1", 30)
    assert ledger.drivers(JOB)[0].heartbeat > driver.heartbeat


def test_a_dead_drivers_tasks_are_claimed_at_once_on_this_machine(
    ledger: Ledger, other_process: subprocess.Popen
) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(3))
    ledger.start_job(JOB, "driver-a", lease=3600, process=process_identity(other_process.pid))
    held = ledger.claim(JOB, "driver-a", 3600, limit=2)
    assert ledger.claimable(JOB) == 1  # driver-a lives: only the free task
    assert ledger.lost_driver(JOB) is None
    other_process.kill()
    other_process.wait(timeout=30)
    lost = ledger.lost_driver(JOB)
    assert lost is not None and lost.driver is not None and lost.driver.driver_id == "driver-a"
    assert lost.since == lost.driver.heartbeat <= time.time()
    started = time.monotonic()
    claims = ledger.claim(JOB, "B", 60, limit=3)
    assert time.monotonic() - started < 5  # the hour-long leases do not matter
    assert [c.task.task_id for c in claims] == [*(c.task.task_id for c in held), "t0002"]
    assert [c.attempt_id[:3] for c in claims] == ["a2-", "a2-", "a1-"]


def test_a_driver_elsewhere_is_lost_when_its_heartbeat_is_older_than_its_lease(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    ledger.start_job(JOB, "far", lease=0.4, process=far_driver())
    ledger.claim(JOB, "far", 0.4)
    ledger.renew(JOB, "far", 0.4)
    assert ledger.lost_driver(JOB) is None
    assert ledger.claim(JOB, "B", 60) == []  # its lease decides
    holders = ledger.holders(JOB)
    assert holders is not None and holders.unknown == ["far"] and holders.live == []
    assert holders.until == ledger.task(JOB, "t0000").lease_expires
    time.sleep(0.6)
    lost = ledger.lost_driver(JOB)
    assert lost is not None and lost.driver is not None and lost.driver.process.host == "far-host"
    assert ledger.holders(JOB) is None
    assert [c.task.task_id for c in ledger.claim(JOB, "B", 60)] == ["t0000"]


def test_a_running_job_without_any_driver_record_is_lost_when_its_leases_lapse(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    ledger.start_job(JOB, "old", lease=0.2, process=far_driver())
    ledger.claim(JOB, "unknown-owner", 0.2)
    time.sleep(0.3)
    ledger.reopen_job(JOB)  # nobody alive: everything back to pending, the lost driver's record gone
    assert ledger.job(JOB).state == PENDING and ledger.drivers(JOB) == []
    ledger.claim(JOB, "unknown-owner", 0.2)
    with ledger._transaction() as db:  # a ledger written before drivers were recorded
        db.execute("UPDATE jobs SET state = ? WHERE job_id = ?", (RUNNING, JOB))
    assert ledger.lost_driver(JOB) is None  # a live lease, holder unknown
    holders = ledger.holders(JOB)
    assert holders is not None and holders.unknown == ["unknown-owner"]
    time.sleep(0.3)
    lost = ledger.lost_driver(JOB)
    assert lost is not None and lost.driver is None
    assert lost.since == ledger.task(JOB, "t0000").lease_expires


def test_leave_gives_back_held_tasks_and_requeues_a_job_nobody_drives(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(3))
    ledger.start_job(JOB, "A")
    ledger.start_job(JOB, "B")
    ledger.claim(JOB, "A", 60)
    ledger.claim(JOB, "B", 60)
    ledger.leave(JOB, "A")
    assert states(ledger) == {"t0000": PENDING, "t0001": RUNNING, "t0002": PENDING}
    assert ledger.job(JOB).state == RUNNING  # B still drives it
    ledger.leave(JOB, "B")
    assert set(states(ledger).values()) == {PENDING}
    assert ledger.job(JOB).state == PENDING and ledger.drivers(JOB) == []
    assert [j.job_id for j in ledger.runnable_jobs()] == [JOB]


def test_reopen_keeps_the_tasks_a_live_driver_runs(ledger: Ledger, other_process: subprocess.Popen) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(4))
    ledger.start_job(JOB, "alive", lease=3600)
    ledger.start_job(JOB, "dead", lease=3600, process=process_identity(other_process.pid))
    (a,) = ledger.claim(JOB, "alive", 3600)
    ledger.claim(JOB, "dead", 3600)
    (f,) = ledger.claim(JOB, "alive", 3600)
    ledger.fail(JOB, f.task.task_id, f.attempt_id, "bad")
    other_process.kill()
    other_process.wait(timeout=30)
    job = ledger.reopen_job(JOB)
    assert job.state == RUNNING  # a resume beside a live driver does not requeue its work
    assert states(ledger) == {"t0000": RUNNING, "t0001": PENDING, "t0002": PENDING, "t0003": PENDING}
    assert ledger.task(JOB, a.task.task_id).lease_owner == "alive"
    assert [x.driver_id for x in ledger.drivers(JOB)] == ["alive"]  # the dead one's record is gone
    holders_before = ledger.holders(JOB)
    assert holders_before is None  # pending tasks can be claimed
    ledger.claim(JOB, "resumer", 60, limit=3)
    holders = ledger.holders(JOB)
    assert holders is not None and [x.driver_id for x in holders.live] == ["alive"]
    assert "resumer" in holders.unknown  # not a recorded driver: its lease decides


def test_fail_job_leaves_a_job_a_live_driver_runs_to_it(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(1))
    ledger.start_job(JOB, "alive")
    job = ledger.fail_job(JOB, "a second driver could not start")
    assert (job.state, job.summary) == (RUNNING, None)
    ledger.leave(JOB, "alive")
    assert ledger.fail_job(JOB, "cannot start").state == FAILED


def test_done_samples_counts_every_drivers_tasks(ledger: Ledger) -> None:
    ledger.create_job(JOB, {}, "/out", task_list(3))
    (a,) = ledger.claim(JOB, "A", 60)
    (b,) = ledger.claim(JOB, "B", 60)
    ledger.complete(JOB, a.task.task_id, a.attempt_id, 5, None)
    ledger.complete(JOB, b.task.task_id, b.attempt_id, 7, None)
    assert ledger.done_samples(JOB) == 12


# ---------------------------------------------------------------------------------------------------------
# several processes on one ledger
# ---------------------------------------------------------------------------------------------------------


def claim_loop(path: str, job_id: str, owner: str, seed: int, barrier, queue) -> None:  # pragma: no cover
    """Claim (1-3 at a time) and complete tasks until none remain; report every claim."""
    rng = random.Random(seed)
    ledger = Ledger(path)
    barrier.wait(timeout=60)
    claimed = []
    idle = 0
    while idle < 3:
        claims = ledger.claim(job_id, owner, 60, limit=rng.randint(1, 3))
        if not claims:
            idle += 1
            time.sleep(0.01)
            continue
        idle = 0
        for claim in claims:
            claimed.append((claim.task.task_id, claim.attempt_id))
            time.sleep(rng.uniform(0.0005, 0.003))  # "work", so that the processes interleave
            assert ledger.complete(job_id, claim.task.task_id, claim.attempt_id, 1, owner)
    ledger.close()
    queue.put((owner, claimed))


def open_and_work(path: str, owner: str, seed: int, barrier, queue) -> None:  # pragma: no cover
    """Open a (fresh) ledger at the same moment as others, add a job, work it off."""
    barrier.wait(timeout=60)
    ledger = Ledger(path)
    ledger.create_job(f"job-{owner}", {}, "/out", task_list(20))
    ledger.close()
    claim_loop(path, f"job-{owner}", owner, seed, _NoBarrier(), queue)


class _NoBarrier:
    def wait(self, timeout: float | None = None) -> None:
        return None


def _run_processes(target, arguments: list[tuple]) -> list[tuple[str, list[tuple[str, str]]]]:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    barrier = context.Barrier(len(arguments))
    processes = [context.Process(target=target, args=(*args, barrier, queue)) for args in arguments]
    for process in processes:
        process.start()
    results = [queue.get(timeout=120) for _ in processes]
    for process in processes:
        process.join(timeout=60)
        assert process.exitcode == 0
    return results


def test_four_processes_claim_every_task_exactly_once(tmp_path: Path) -> None:
    path = tmp_path / "ledger.db"
    setup = Ledger(path)
    setup.create_job(JOB, {}, "/out", task_list(200))
    setup.close()
    results = _run_processes(claim_loop, [(str(path), JOB, f"owner-{i}", i) for i in range(4)])
    claimed = [task_id for _, claims in results for task_id, _ in claims]
    assert len(claimed) == 200
    assert sorted(claimed) == [f"t{i:04d}" for i in range(200)]  # every task once, none twice
    assert all(claims for _, claims in results), "every process got some work"
    check = Ledger(path)
    tasks = check.tasks(JOB)
    owners = {task_id: owner for owner, claims in results for task_id, _ in claims}
    assert all(t.state == DONE and t.attempts == 1 for t in tasks)
    assert all(t.placement == owners[t.task_id] for t in tasks)
    assert check.task_counts(JOB) == {DONE: 200}
    check.close()


def test_processes_opening_a_fresh_ledger_together(tmp_path: Path) -> None:
    path = tmp_path / "new" / "ledger.db"
    results = _run_processes(open_and_work, [(str(path), f"p{i}", i) for i in range(4)])
    check = Ledger(path)
    assert len(check.jobs()) == 4
    for owner, claims in results:
        assert sorted(t for t, _ in claims) == [f"t{i:04d}" for i in range(20)]
        assert check.task_counts(f"job-{owner}") == {DONE: 20}
    check.close()
