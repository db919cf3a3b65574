"""Faults with real processes and a real Ray: a Ray worker SIGKILLed mid-task (and every worker of
one task, until Ray gives up), the driver SIGKILLed mid-job (`status` says so) and resumed, a
`resume` beside the still-running driver, a job cancelled while it runs, and two `datagen serve`
drivers on one ledger. Each must end with exactly the samples of an uninterrupted run (or,
cancelled, with readable committed shards), every task computed once where the ledger says so; a
task that cannot be computed is named in the dataset's failure records.

The uninterrupted reference and the worker kill run in this process on one private Ray (2 CPUs);
the other tests run `datagen` subprocesses (each with its own Ray) after that Ray is shut down.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
from support.engine import (
    SIX_BUILTINS,
    assert_same_samples,
    builtin_lines,
    check_complete_dataset,
    datagen_processes,
    done_count,
    job_tasks,
    kill_exact,
    only_job,
    open_ledger,
    planned_task_ids,
    ray_task_workers,
    run_datagen,
    shard_dirs,
    start_local_ray,
    stop_local_ray,
    summarize,
    wait_for_done_tasks,
    wait_until,
    write_config,
    write_objects,
)

from datagen import api
from datagen.engine import driver as driver_module
from datagen.settings import RunSettings
from jobs.ledger import CANCELLED, DONE, FAILED, PENDING, RUNNING
from storage import committed_tasks, open_dataset, open_location, read_failures, validate

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fault tests read /proc (Linux)"),
    pytest.mark.slow,
    pytest.mark.ray,
]

RAY_CPUS = 2
TASKS = len(SIX_BUILTINS) * 2


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    write_config(folder / "fast.toml", rotations=2)
    write_objects(folder / "six.txt", builtin_lines(SIX_BUILTINS))
    return folder


@pytest.fixture(scope="module")
def local_ray():
    start_local_ray(RAY_CPUS)
    yield
    stop_local_ray()


@pytest.fixture
def no_local_ray() -> None:
    """Subprocess tests: give this process's Ray CPUs back to the machine first."""
    stop_local_ray()


def settings_for(home: Path) -> RunSettings:
    return RunSettings(home=home, num_workers=RAY_CPUS, ray_address=None)


@pytest.fixture(scope="module")
def reference(inputs: Path, local_ray, tmp_path_factory):
    """The uninterrupted run of 6 built-ins x 2 rotations."""
    home = tmp_path_factory.mktemp("reference")
    job = api.submit(inputs / "six.txt", inputs / "fast.toml", settings_for(home))
    assert job.state == DONE, job.summary
    task_ids = planned_task_ids(home, job.job_id)
    assert len(task_ids) == TASKS
    summary = check_complete_dataset(job.out, task_ids)
    return job, summary


def submit_args(inputs: Path) -> list[str]:
    return ["submit", "--objects", str(inputs / "six.txt"), "--config", str(inputs / "fast.toml")]


# ---------------------------------------------------------------------------------------------------------
# (a) a Ray worker dies mid-task
# ---------------------------------------------------------------------------------------------------------


def test_worker_sigkill_mid_job(reference, inputs: Path, local_ray, tmp_path: Path) -> None:
    ref_job, ref_summary = reference
    home = tmp_path / "home"
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["job"] = api.submit(inputs / "six.txt", inputs / "fast.toml", settings_for(home))
        except BaseException as exc:  # reported by the main thread
            outcome["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    killed = []
    deadline = time.monotonic() + 180
    # first kill: the first task running; second kill: a task started after some are done
    while thread.is_alive() and len(killed) < 2 and time.monotonic() < deadline:
        busy = ray_task_workers(os.getpid())
        if busy and (not killed or done_count(home) >= 4) and all(b.pid != k.pid for b in busy for k in killed):
            kill_exact(busy[:1])
            killed.append(busy[0])
        time.sleep(0.02)
    thread.join(timeout=240)
    assert not thread.is_alive(), "the job did not finish"
    assert "error" not in outcome, outcome.get("error")
    assert len(killed) >= 1, "no Ray worker was seen running a task"
    job = outcome["job"]
    assert job.state == DONE, job.summary
    summary = check_complete_dataset(job.out, list(ref_summary.commits))
    assert summary.samples == ref_summary.samples
    assert sorted(summary.sample_ids) == sorted(ref_summary.sample_ids)
    assert_same_samples(job.out, ref_job.out)
    # Ray re-ran the killed tasks inside the ledger's attempt: nothing failed, nothing claimed twice
    tasks = job_tasks(home, job.job_id)
    assert all(t.state == DONE and t.attempts == 1 for t in tasks), [(t.task_id, t.attempts) for t in tasks]
    assert job.summary is not None and job.summary["samples"] == ref_summary.samples


def test_worker_deaths_fail_the_task_with_a_failure_record(
    local_ray, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every worker that runs the task is killed until Ray's retries are spent: the task is failed
    in the ledger and in the dataset, whose failure record (and `datagen shards ls`) names it, its
    objects-file line, what happened and the fix."""
    monkeypatch.setattr(driver_module, "TASK_RETRIES", 1)  # two deaths are enough
    config = write_config(tmp_path / "one.toml", rotations=1)
    objects = write_objects(tmp_path / "one.txt", builtin_lines(["mug"]))
    home = tmp_path / "home"
    outcome: dict[str, object] = {}

    def run() -> None:
        try:
            outcome["job"] = api.submit(objects, config, settings_for(home))
        except BaseException as exc:  # reported by the main thread
            outcome["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    killed: list = []
    deadline = time.monotonic() + 180
    while thread.is_alive() and time.monotonic() < deadline:
        fresh = [b for b in ray_task_workers(os.getpid()) if all(b.pid != k.pid for k in killed)]
        kill_exact(fresh)
        killed += fresh
        time.sleep(0.02)
    thread.join(timeout=60)
    assert not thread.is_alive(), "the job did not finish"
    assert "error" not in outcome, outcome.get("error")
    assert len(killed) == 2, killed
    job = outcome["job"]
    assert job.state == FAILED, job.summary
    (task,) = job_tasks(home, job.job_id)
    assert (task.state, task.attempts) == (FAILED, 1)
    assert task.error.startswith("worker error: its worker process died 2 times running it")
    (record,) = read_failures(open_location(job.out))
    assert (record.task_id, record.object_name, record.origin) == (task.task_id, "mug", f"{objects}:2")
    assert "died 2 times" in record.message and f"then `datagen resume {job.job_id}`" in record.message
    listing = run_datagen(["shards", "ls", job.out], timeout=120)
    assert listing.returncode == 0, listing.stdout + listing.stderr
    assert ", 1 failed" in listing.stdout, listing.stdout
    assert f"failed {task.task_id} ({objects}:2): its worker process died 2 times" in listing.stdout


# ---------------------------------------------------------------------------------------------------------
# (b) the driver dies mid-job; `datagen resume` finishes it
# ---------------------------------------------------------------------------------------------------------


def test_driver_sigkill_then_resume(reference, no_local_ray, inputs: Path, tmp_path: Path) -> None:
    ref_job, ref_summary = reference
    home = tmp_path / "home"
    with datagen_processes() as start:
        driver = start([*submit_args(inputs), "--workers", "1", "--home", str(home)], tmp_path / "submit.log")

        wait_for_done_tasks(driver, home, 3, before="kill")
        driver.sigkill()
        job = only_job(home)
        assert job is not None
        # the ledger shows the job's driver as gone, and says what to do
        status = run_datagen(["status", job.job_id, "--home", str(home)], timeout=120)
        assert status.returncode == 0, status.stdout + status.stderr
        assert "running (driver lost" in status.stdout, status.stdout
        assert f"job {job.job_id}: its driver (pid {driver.pid} on " in status.stdout, status.stdout
        assert f"run `datagen resume {job.job_id}` to finish it" in status.stdout, status.stdout
        before = {t.task_id: t for t in job_tasks(home, job.job_id)}
        done_before = {task_id for task_id, t in before.items() if t.state == DONE}
        assert 3 <= len(done_before) < TASKS, "the kill did not land mid-job"
        assert any(t.state in (PENDING, RUNNING) for t in before.values())
        commits_before = {r.task_id: r.attempt_id for r in committed_tasks(open_location(job.out))}
        assert done_before <= set(commits_before)
        files_before = shard_dirs(job.out)
        driver.close()  # the dead driver's Ray leftovers

        resume = start(["resume", job.job_id, "--home", str(home), "--workers", "2"], tmp_path / "resume.log")
        assert resume.wait(timeout=240) == 0, resume.output()
    # the dead driver's tasks were taken at once: the job was done before its leases would lapse
    leases = [t.lease_expires for t in before.values() if t.state == RUNNING and t.lease_expires]
    assert leases and time.time() < max(leases), "the resume waited for the dead driver's leases"
    job = only_job(home)
    assert job is not None and job.state == DONE
    summary = check_complete_dataset(job.out, list(ref_summary.commits))
    assert sorted(summary.sample_ids) == sorted(ref_summary.sample_ids)
    assert_same_samples(job.out, ref_job.out)
    after = {t.task_id: t for t in job_tasks(home, job.job_id)}
    assert all(t.state == DONE for t in after.values())
    for task_id in done_before:  # finished shards are not recomputed
        assert after[task_id].attempts == 1
        assert after[task_id].attempt_id == before[task_id].attempt_id
        assert after[task_id].samples == before[task_id].samples
    for task_id, attempt in commits_before.items():  # nor is anything committed before the kill
        assert summary.commits[task_id] == attempt
        assert shard_dirs(job.out)[task_id] == files_before[task_id]
    # the tasks the dead driver held or never reached ran under a fresh ledger attempt
    for task_id, task in before.items():
        if task.state == RUNNING:
            assert after[task_id].attempts == 2
        elif task.state == PENDING:
            assert after[task_id].attempts == 1


def test_resume_beside_the_running_driver(reference, no_local_ray, inputs: Path, tmp_path: Path) -> None:
    """`datagen resume` while the job's `submit` still runs: the two drivers share what is left
    (neither takes a task the other runs), both wait for the job's end and report it done (exit 0)
    with the sample count of the whole dataset."""
    ref_job, ref_summary = reference
    home = tmp_path / "home"
    with datagen_processes() as start:
        first = start([*submit_args(inputs), "--workers", "1", "--home", str(home)], tmp_path / "submit.log")

        wait_for_done_tasks(first, home, 2, before="resume")
        job = only_job(home)
        assert job is not None
        second = start(["resume", job.job_id, "--home", str(home), "--workers", "1"], tmp_path / "resume.log")
        assert second.wait(timeout=300) == 0, second.output()
        assert first.wait(timeout=300) == 0, first.output()
        logs = [first.output(), second.output()]
    job = only_job(home)
    assert job is not None and job.state == DONE, logs
    summary = check_complete_dataset(job.out, list(ref_summary.commits))
    assert summary.samples == ref_summary.samples
    assert_same_samples(job.out, ref_job.out)
    for log in logs:
        assert f"job {job.job_id} done" in log, log
        assert f"{TASKS}/{TASKS} tasks done, {summary.samples} samples, 0 failed" in log, log
    tasks = job_tasks(home, job.job_id)
    assert all(t.state == DONE and t.attempts == 1 for t in tasks), [(t.task_id, t.attempts) for t in tasks]
    assert all(len(files) == 2 for files in shard_dirs(job.out).values()), shard_dirs(job.out)
    print(f"tasks per driver: {sorted(Counter(t.placement for t in tasks).values())}")


# ---------------------------------------------------------------------------------------------------------
# (c) cancel while the job runs
# ---------------------------------------------------------------------------------------------------------


def test_cancel_while_submit_runs(no_local_ray, inputs: Path, tmp_path: Path) -> None:
    home = tmp_path / "home"
    with datagen_processes() as start:
        driver = start([*submit_args(inputs), "--workers", "1", "--home", str(home)], tmp_path / "submit.log")

        wait_for_done_tasks(driver, home, 2, before="cancel")
        job = only_job(home)
        assert job is not None
        cancelled_at = time.monotonic()
        result = run_datagen(["cancel", job.job_id, "--home", str(home)])
        assert result.returncode == 0, result.stdout + result.stderr
        assert f"job {job.job_id}: cancelled" in result.stdout
        code = driver.wait(timeout=120)
        stopped_after = time.monotonic() - cancelled_at
        assert code != 0, driver.output()
        assert "cancelled" in driver.output()
    assert stopped_after < 30, f"the driver took {stopped_after:.1f} s to stop"
    with open_ledger(home) as ledger:
        job = ledger.job(job.job_id)
        counts = ledger.task_counts(job.job_id)
        tasks = ledger.tasks(job.job_id)
    assert job.state == CANCELLED
    assert counts.get(DONE, 0) >= 2 and counts.get(CANCELLED, 0) >= 1
    assert not counts.get(PENDING) and not counts.get(RUNNING), counts
    # what is committed stays readable and sound
    assert validate(job.out, full=True) == []
    dataset = open_dataset(job.out)
    commits = committed_tasks(open_location(job.out))
    assert {t.task_id for t in tasks if t.state == DONE} <= {r.task_id for r in commits}
    assert len(dataset) == sum(r.num_samples for r in commits) == summarize(job.out).planned
    for i in range(len(dataset)):
        sample = dataset[i]
        assert sample["points"].shape[1] == 3 and sample["label"].shape == (dataset.num_views,)


# ---------------------------------------------------------------------------------------------------------
# two drivers on one ledger
# ---------------------------------------------------------------------------------------------------------


def test_two_serves_run_every_task_once(reference, no_local_ray, inputs: Path, tmp_path: Path) -> None:
    ref_job, ref_summary = reference
    home = tmp_path / "home"
    queued = run_datagen([*submit_args(inputs), "--detach", "--home", str(home)])
    assert queued.returncode == 0, queued.stdout + queued.stderr
    job = only_job(home)
    assert job is not None and job.state == PENDING
    serve = ["serve", "--once", "--home", str(home), "--workers", "1", "--poll", "0.5"]
    with datagen_processes() as start:
        first = start(serve, tmp_path / "serve1.log")
        second = start(serve, tmp_path / "serve2.log")
        assert first.wait(timeout=300) == 0, first.output()
        assert second.wait(timeout=300) == 0, second.output()
        logs = [first.output(), second.output()]
    job = only_job(home)
    assert job is not None and job.state == DONE, logs
    tasks = job_tasks(home, job.job_id)
    assert all(t.state == DONE and t.attempts == 1 for t in tasks), [(t.task_id, t.state, t.attempts) for t in tasks]
    # one execution per task: one shard group + one index fragment, one commit, no duplicate samples
    assert all(len(files) == 2 for files in shard_dirs(job.out).values()), shard_dirs(job.out)
    summary = check_complete_dataset(job.out, list(ref_summary.commits))
    assert_same_samples(job.out, ref_job.out)
    placements = {t.placement for t in tasks}
    print(f"placements: {sorted(placements)}; 'running job' lines per serve: {[s.count('running job') for s in logs]}")
    assert summary.samples == ref_summary.samples


# ---------------------------------------------------------------------------------------------------------
# a serve waiting on another driver's lease
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def serve_waiting_on_a_lease(tmp_path_factory):
    """`serve --once --poll 1` on a one-task job whose task another (live) driver holds; after the
    serve has looked at the job for 3 s, that driver gives the task back. Returns the 'running job'
    lines printed in those 3 s, the serve's exit code and output, the home and the job id."""
    stop_local_ray()
    folder = tmp_path_factory.mktemp("lease")
    home = folder / "home"
    write_config(folder / "one.toml", rotations=1)
    write_objects(folder / "one.txt", builtin_lines(["capsule"]))
    job = api.enqueue(folder / "one.txt", folder / "one.toml", RunSettings(home=home, ray_address=None))
    with open_ledger(home) as ledger:
        (held,) = ledger.claim(job.job_id, "other-driver", 600)
    serve = ["serve", "--once", "--home", str(home), "--workers", "1", "--poll", "1"]
    with datagen_processes() as start:
        process = start(serve, folder / "serve.log")

        def said_it_waits() -> bool:
            assert process.poll() is None, process.output()
            return "waiting for" in process.output()  # it looked at the job and found the task held

        wait_until(said_it_waits, timeout=180, interval=0.05, what="the serve to look at the job")
        first = process.output().count("running job")
        time.sleep(3.0)
        in_window = process.output().count("running job") - first
        with open_ledger(home) as ledger:
            assert ledger.release(job.job_id, held.task.task_id, held.attempt_id)
        code = process.wait(timeout=180)
        output = process.output()
    return in_window, code, output, home, job.job_id


def test_serve_takes_a_task_given_back_by_another_driver(serve_waiting_on_a_lease) -> None:
    _, code, output, home, job_id = serve_waiting_on_a_lease
    assert code == 0, output
    with open_ledger(home) as ledger:
        job = ledger.job(job_id)
        (task,) = ledger.tasks(job_id)
    assert job.state == DONE
    assert (task.state, task.attempts) == (DONE, 2)
    check_complete_dataset(job.out, [task.task_id])


def test_serve_polls_while_another_driver_holds_the_tasks(serve_waiting_on_a_lease) -> None:
    in_window, *_ = serve_waiting_on_a_lease
    assert in_window <= 10, f"{in_window} calls of run_job in 3 s with --poll 1"


def test_serve_says_once_what_it_waits_for_and_until_when(serve_waiting_on_a_lease) -> None:
    _, _, output, _, job_id = serve_waiting_on_a_lease
    waiting = [line for line in output.splitlines() if "waiting for" in line]
    assert len(waiting) == 1, output  # once, not at every poll
    assert waiting[0].startswith(
        f"job {job_id}: waiting for 1 task held by other-driver; until they finish, or their leases lapse at "
    ), waiting
    assert output.count("running job") == 1, output  # run_job only once the task could be claimed


# ---------------------------------------------------------------------------------------------------------
# a job that cannot start must not stop the serve
# ---------------------------------------------------------------------------------------------------------


def test_serve_fails_a_job_that_cannot_start_and_goes_on(no_local_ray, tmp_path: Path) -> None:
    from datagen.engine.driver import dataset_info
    from schemas.config import GenerationConfig
    from storage import init_dataset

    out = tmp_path / "taken"
    write_config(tmp_path / "one.toml", rotations=1)
    write_objects(tmp_path / "one.txt", builtin_lines(["capsule"]))
    home = tmp_path / "home"
    job = api.enqueue(tmp_path / "one.txt", tmp_path / "one.toml", RunSettings(home=home, out=str(out)))
    # Another job's dataset takes the folder after this job was queued (submit refuses it before that).
    init_dataset(open_location(str(out)), dataset_info(GenerationConfig(rotations=3, refiner="none")))
    result = run_datagen(["serve", "--once", "--home", str(home), "--workers", "1", "--poll", "0.2"], timeout=120)
    with open_ledger(home) as ledger:
        state = ledger.job(job.job_id).state
    assert "another config" in result.stdout + result.stderr
    assert state == FAILED, state
    assert result.returncode == 0, result.stdout + result.stderr
