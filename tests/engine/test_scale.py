"""The engine's scale case in small (benchmarks/scale/engine.py runs it at 1k-100k tasks): a job of
200 tasks through the real ledger, the real driver and a local Ray, over `empty_task` (a body that
computes and writes nothing), so only the engine's own behaviour is under test. Every task runs
once; the ledger's counts, done samples and the job summary agree with the rows; progress reaches
the total; cancel, resume and a resume with nothing left keep their meaning; two drivers on one job
share its tasks, each task run once; `datagen status JOB` lists every task.

One private Ray (2 CPUs) serves the module, as in test_engine.py.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from support.engine import job_tasks, open_ledger, start_local_ray, stop_local_ray, write_config, write_objects
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli.main import app
from datagen.engine.driver import JobProgress, run_job
from datagen.engine.worker import empty_task
from datagen.settings import RunSettings
from jobs.ledger import CANCELLED, DONE, PENDING, Ledger

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.ray,
]

RAY_CPUS = 2
OBJECTS = 25
ROTATIONS = 8
TASKS = OBJECTS * ROTATIONS


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    start_local_ray(RAY_CPUS)
    yield
    stop_local_ray()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """25 distinct objects (seeded variants of one built-in: nothing to read) at 8 rotations."""
    folder = tmp_path_factory.mktemp("inputs")
    write_config(folder / "eight.toml", rotations=ROTATIONS)
    write_objects(folder / "objects.txt", [f"builtin:capsule variant={seed}" for seed in range(OBJECTS)])
    return folder


def settings_for(home: Path) -> RunSettings:
    return RunSettings(home=home, num_workers=RAY_CPUS, ray_address=None)


def enqueue(inputs: Path, home: Path) -> str:
    return api.enqueue(inputs / "objects.txt", inputs / "eight.toml", settings_for(home)).job_id


def expected_samples() -> int:
    """What `empty_task` reports: rotation + 1 samples a task."""
    return OBJECTS * sum(rotation + 1 for rotation in range(ROTATIONS))


def assert_ledger_agrees(home: Path, job_id: str) -> None:
    """The counts and samples the ledger keeps equal those of its task rows."""
    tasks = job_tasks(home, job_id)
    with open_ledger(home) as ledger:
        assert ledger.task_counts(job_id) == dict(Counter(t.state for t in tasks))
        assert ledger.done_samples(job_id) == sum(t.samples or 0 for t in tasks if t.state == DONE)


def test_a_job_of_200_empty_tasks_runs_every_task_once(inputs: Path, tmp_path: Path) -> None:
    seen: list[tuple[int, int, int]] = []

    def progress(state: JobProgress) -> None:
        seen.append((state.total, state.done, state.samples))

    home = tmp_path / "home"
    job = api.submit(inputs / "objects.txt", inputs / "eight.toml", settings_for(home), progress, body=empty_task)
    assert job.state == DONE, job.summary
    assert job.summary is not None
    assert (job.summary["tasks"], job.summary["done"], job.summary["failed"]) == (TASKS, TASKS, 0)
    assert job.summary["samples"] == 0  # empty_task writes nothing: the dataset holds no sample
    tasks = job_tasks(home, job.job_id)
    assert len(tasks) == TASKS and len({t.task_id for t in tasks}) == TASKS
    for task in tasks:
        assert (task.state, task.attempts, task.error) == (DONE, 1, None)
        assert task.samples == task.spec["rotation"] + 1 and task.placement and "@" in task.placement
    assert_ledger_agrees(home, job.job_id)
    with open_ledger(home) as ledger:
        assert ledger.done_samples(job.job_id) == expected_samples()
        assert ledger.drivers(job.job_id) == []  # the driver left
    assert {total for total, _, _ in seen} == {TASKS}
    assert [done for _, done, _ in seen] == sorted(done for _, done, _ in seen)  # never goes back
    assert seen[-1] == (TASKS, TASKS, expected_samples())


def test_cancel_then_resume_then_resume_with_nothing_left(inputs: Path, tmp_path: Path) -> None:
    home = tmp_path / "home"
    job_id = enqueue(inputs, home)
    assert api.cancel(job_id, settings_for(home)).state == CANCELLED
    assert Counter(t.state for t in job_tasks(home, job_id)) == {CANCELLED: TASKS}
    assert_ledger_agrees(home, job_id)

    job = api.resume(job_id, settings_for(home), body=empty_task)
    assert job.state == DONE and job.summary is not None and job.summary["done"] == TASKS
    assert all((t.state, t.attempts) == (DONE, 1) for t in job_tasks(home, job_id))

    again = api.resume(job_id, settings_for(home), body=empty_task)  # nothing is run again
    assert again.state == DONE and again.summary is not None and again.summary["done"] == TASKS
    assert all((t.state, t.attempts) == (DONE, 1) for t in job_tasks(home, job_id))
    assert_ledger_agrees(home, job_id)


def test_two_drivers_on_one_job_share_its_tasks(inputs: Path, tmp_path: Path) -> None:
    home = tmp_path / "home"
    job_id = enqueue(inputs, home)
    outcomes: dict[int, Any] = {}

    def drive(number: int) -> None:
        ledger = Ledger(home / api.LEDGER_FILE)
        try:
            outcomes[number] = run_job(ledger, job_id, num_cpus=RAY_CPUS, body=empty_task).state
        except Exception as error:  # reported below, with the other driver's outcome
            outcomes[number] = error
        finally:
            ledger.close()

    threads = [threading.Thread(target=drive, args=(number,)) for number in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=300)
    assert outcomes == {0: DONE, 1: DONE}
    tasks = job_tasks(home, job_id)
    assert all((t.state, t.attempts) == (DONE, 1) for t in tasks)  # claims exclusive: each task ran once
    assert_ledger_agrees(home, job_id)


def test_status_lists_every_task_and_the_counts(inputs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    home = tmp_path / "home"
    job_id = enqueue(inputs, home)
    monkeypatch.setattr(common.console, "_width", 400)
    result = CliRunner().invoke(app, ["status", job_id, "--home", str(home)])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    # Off a terminal both tables are whole tab-separated lines: the job's, then its tasks'.
    assert lines[0].split("\t") == ["job", "state", "tasks", "done", "failed", "running", "dataset"]
    assert lines[1].split("\t")[:6] == [job_id, PENDING, str(TASKS), "0", "0", "0"]
    rows = [line.split("\t") for line in lines[2:] if "\t" in line]
    assert rows[0] == ["task", "state", "attempts", "samples", "placement", "error"]
    assert [row[0] for row in rows[1:]] == [t.task_id for t in job_tasks(home, job_id)]
    assert {row[1] for row in rows[1:]} == {PENDING}
    listing = CliRunner().invoke(app, ["status", "--home", str(home)])  # every job: the id whole in a pipe
    assert listing.exit_code == 0 and [job_id, PENDING] == listing.stdout.splitlines()[1].split("\t")[:2]
    as_json = CliRunner().invoke(app, ["status", job_id, "--home", str(home), "--json"])  # what a script reads
    assert as_json.exit_code == 0, as_json.output
    found = json.loads(as_json.stdout)
    assert [(j["job_id"], j["state"], j["tasks"], j["counts"]) for j in found["jobs"]] == [
        (job_id, PENDING, TASKS, {PENDING: TASKS})
    ]
    assert [t["task_id"] for t in found["tasks"]] == [t.task_id for t in job_tasks(home, job_id)]
    assert all(t["state"] == PENDING and t["attempts"] == 0 for t in found["tasks"])
    every = json.loads(CliRunner().invoke(app, ["status", "--home", str(home), "--json"]).stdout)
    assert "tasks" not in every and [j["job_id"] for j in every["jobs"]] == [job_id]
