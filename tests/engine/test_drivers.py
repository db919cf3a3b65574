"""Drivers seen from outside, without Ray: `datagen status` names a job whose driver is gone, the
serve loop waits for another driver's leases with one line (and leaves a job to a live driver of
this machine), a dead driver's job is taken at once, and the job report puts each error on stderr
in one unwrapped line. `run_job` is replaced by a stand-in that works off the ledger; the real
engine is covered by tests/system/test_faults.py."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli import jobs as jobs_cli
from datagen.cli.main import app
from datagen.engine import serve as serve_module
from datagen.engine.serve import serve
from datagen.settings import RunSettings, ledger_for
from jobs.ledger import DONE, RUNNING, Job, Ledger
from jobs.liveness import process_identity


@pytest.fixture
def home(tmp_path: Path) -> Path:
    return tmp_path / "home"


@pytest.fixture
def job_id(tmp_path: Path, home: Path) -> str:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    config = tmp_path / "one.toml"
    config.write_text('rotations = 1\nrefiner = "none"\n')
    return api.enqueue(objects, config, RunSettings(home=home, out=str(tmp_path / "out"))).job_id


@pytest.fixture
def ledger(home: Path, job_id: str) -> Iterator[Ledger]:
    led = ledger_for(RunSettings(home=home))
    yield led
    led.close()


@pytest.fixture
def doomed() -> Iterator[subprocess.Popen]:
    """A process of this machine that stands for a driver about to be killed."""
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    yield process
    if process.poll() is None:
        process.kill()
        process.wait(timeout=30)


def kill(process: subprocess.Popen) -> None:
    process.kill()
    process.wait(timeout=30)


def serve_once(home: Path, timeout: float = 30.0) -> list[str]:
    """`serve(once=True)` in a thread (so that a loop that never ends fails the test); its lines."""
    lines: list[str] = []
    thread = threading.Thread(
        target=serve, args=(RunSettings(home=home),), kwargs={"poll": 0.05, "once": True, "report": lines.append}
    )
    thread.daemon = True
    thread.start()
    thread.join(timeout=timeout)
    assert not thread.is_alive(), f"serve --once still runs after {timeout} s: {lines[:6]}"
    return lines


def fake_run_job(calls: list[str]):
    """Stands for `run_job`: claims what it can, completes it, finishes the job when all is done."""

    def run(ledger: Ledger, job_id: str, **kwargs: object) -> Job:
        calls.append(job_id)
        for claim in ledger.claim(job_id, "fake-driver", 60, limit=100):
            ledger.complete(job_id, claim.task.task_id, claim.attempt_id, 3, "here")
        counts = ledger.task_counts(job_id)
        if not counts.get("pending") and not counts.get("running"):
            ledger.finish_job(job_id, {"samples": ledger.done_samples(job_id)})
        return ledger.job(job_id)

    return run


# ---------------------------------------------------------------------------------------------------------
# serve
# ---------------------------------------------------------------------------------------------------------


def test_serve_once_reports_its_wait_for_another_drivers_lease_once(
    home: Path, job_id: str, ledger: Ledger, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(serve_module, "run_job", fake_run_job(calls))
    (held,) = ledger.claim(job_id, "other-driver", 600)
    lines: list[str] = []
    thread = threading.Thread(
        target=serve, args=(RunSettings(home=home),), kwargs={"poll": 0.02, "once": True, "report": lines.append}
    )
    thread.daemon = True
    thread.start()
    time.sleep(1.0)  # about 50 looks at the queue
    assert thread.is_alive() and calls == []
    assert ledger.release(job_id, held.task.task_id, held.attempt_id)
    thread.join(timeout=30)
    assert not thread.is_alive()
    waiting = [line for line in lines if "waiting for" in line]
    until = time.strftime("%H:%M:%S", time.localtime(held.task.lease_expires or 0))
    assert waiting == [
        f"job {job_id}: waiting for 1 task held by other-driver; "
        f"until they finish, or their leases lapse at {until} unless renewed"
    ]
    assert lines[-2:] == [f"running job {job_id}", f"job {job_id}: done"]
    assert calls == [job_id]


def test_serve_once_leaves_a_job_to_a_live_driver_of_this_machine(
    home: Path, job_id: str, ledger: Ledger, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(serve_module, "run_job", fake_run_job(calls))
    ledger.start_job(job_id, "live-driver")  # this test process: alive
    ledger.claim(job_id, "live-driver", 600)
    lines = serve_once(home, timeout=10)
    me = process_identity()
    assert lines[1:] == [
        f"job {job_id}: its last 1 task run under driver pid {me.pid} on {me.host} (alive); leaving the job to it"
    ]
    assert calls == []


def test_serve_takes_a_dead_drivers_job_at_once(
    home: Path, job_id: str, ledger: Ledger, doomed: subprocess.Popen, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    monkeypatch.setattr(serve_module, "run_job", fake_run_job(calls))
    ledger.start_job(job_id, "doomed-driver", lease=3600, process=process_identity(doomed.pid))
    ledger.claim(job_id, "doomed-driver", 3600)
    kill(doomed)
    lines = serve_once(home, timeout=10)  # not the hour of its lease
    assert lines[1:] == [f"running job {job_id}", f"job {job_id}: done"]
    (task,) = ledger.tasks(job_id)
    assert (task.state, task.attempts) == (DONE, 2)


# ---------------------------------------------------------------------------------------------------------
# status
# ---------------------------------------------------------------------------------------------------------


def status_output(home: Path, *args: str, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(common.console, "_width", 400)  # table cells whole
    result = CliRunner().invoke(app, ["status", *args, "--home", str(home)])
    assert result.exit_code == 0, result.output
    return result.stdout


def test_status_shows_a_job_whose_driver_died_as_lost(
    home: Path, job_id: str, ledger: Ledger, doomed: subprocess.Popen, monkeypatch: pytest.MonkeyPatch
) -> None:
    ledger.start_job(job_id, "doomed-driver", lease=3600, process=process_identity(doomed.pid))
    ledger.claim(job_id, "doomed-driver", 3600)
    alive = status_output(home, monkeypatch=monkeypatch)
    assert "driver lost" not in alive and "\trunning\t" in alive
    kill(doomed)
    # The age is read off a fixed clock: 42 s after the driver's last heartbeat, however long the
    # machine took to get here (a loaded CI machine read "1 s ago" where "0 s" was expected).
    heartbeat = max(driver.heartbeat for driver in ledger.drivers(job_id))
    monkeypatch.setattr(time, "time", lambda: heartbeat + 42.0)
    for output in (status_output(home, monkeypatch=monkeypatch), status_output(home, job_id, monkeypatch=monkeypatch)):
        assert "running (driver lost 42 s ago)" in output, output
        assert f"job {job_id}: its driver (pid {doomed.pid} on " in output
        assert f"run `datagen resume {job_id}` to finish it" in output
    assert "running (driver lost)" in status_output(home, job_id, monkeypatch=monkeypatch)  # the task row
    assert ledger.job(job_id).state == RUNNING  # status only reads


# ---------------------------------------------------------------------------------------------------------
# the job report
# ---------------------------------------------------------------------------------------------------------


def test_report_puts_each_error_on_stderr_in_one_unwrapped_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(common.console, "_width", 80)
    monkeypatch.setattr(common.error_console, "_width", 80)
    failure = "/a/rather/long/path/to/an/objects/file/objects.txt:12: t-0001: " + "mesh is not watertight " * 5
    line_error = "/a/rather/long/path/to/an/objects/file/objects.txt:3: missing.obj: mesh file not found here"
    summary = {"tasks": 2, "done": 1, "failed": 1, "refused_lines": 1, "samples": 7}
    summary |= {"failures": [failure], "line_errors": [line_error]}
    job = Job("j-1", "failed", {}, "/a/rather/long/path/to/the/dataset/" + "x" * 60, 0.0, 0.0, None, summary)
    jobs_cli._report(job)
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"error: {line_error}", f"error: {failure}"]
    assert "error:" not in captured.out
    # the objects file's refused lines are not counted as tasks (issue 42: "1/2 tasks done ... 3 failed")
    assert "1/2 tasks done, 7 samples, 1 failed; 1 objects-file line refused" in captured.out
    assert f"dataset: {job.out}" in captured.out.splitlines()
