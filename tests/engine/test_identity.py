"""The dataset's identity includes the content of the files its config names, the shipped POCO
weights too: `datagen resume` refuses (one line, before Ray starts) to add to a dataset made with
other weights, and a worker whose weights differ from the dataset's fails its task instead of mixing
two refiners. No Ray: the refusal comes first, and the worker is called directly."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.engine import QueuedJob, planned_tasks, queued_job
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli.main import app
from datagen.engine import driver as driver_module
from datagen.engine.worker import execute_task
from datagen.settings import RunSettings
from jobs.ledger import FAILED
from schemas import config as config_module
from schemas.jobs import JobSpec
from storage import open_location, read_commit, read_failures, read_info


def upgraded_weights(tmp_path: Path) -> Path:
    """A copy of the shipped weights with one byte changed: the weights of a later release."""
    data = bytearray(config_module.builtin_poco_weights().read_bytes())
    data[len(data) // 2] ^= 0x01
    path = tmp_path / "upgraded" / "poco_small.pt"
    path.parent.mkdir()
    path.write_bytes(bytes(data))
    return path


@pytest.fixture
def poco_job(tmp_path: Path) -> QueuedJob:
    """A queued poco job whose dataset the first run made with the shipped weights."""
    return queued_job(tmp_path, 'rotations = 1\nrefiner = "poco"\npoco_weights = "builtin"\n')


def test_resume_refuses_a_dataset_made_with_other_builtin_weights(
    tmp_path: Path, poco_job: QueuedJob, monkeypatch: pytest.MonkeyPatch
) -> None:
    home, job, made = poco_job.home, poco_job.job, poco_job.made
    new = upgraded_weights(tmp_path)
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", new)

    def no_ray(*args: object) -> None:
        raise AssertionError("resume started Ray instead of refusing")

    monkeypatch.setattr(driver_module, "ensure_ray", no_ray)
    monkeypatch.setattr(common.error_console, "_width", 80)
    result = CliRunner().invoke(app, ["resume", job.job_id, "--home", str(home)])
    assert result.exit_code == common.EXIT_USER_ERROR, (result.output, result.exception)
    (line,) = result.stderr.splitlines()  # one line, not wrapped at 80 columns
    assert line.startswith(f"error: {job.out}: was made with this config but other contents of the files it names")
    assert f"poco_weights = {new}" in line and made.config_hash[:12] in line
    assert "restore the files it was made with, or write to a new --out" in line
    # nothing was added to the dataset, and the ledger says why the job stopped
    assert read_info(open_location(job.out)).config_hash == made.config_hash
    assert read_commit(open_location(job.out), planned_tasks(home, job.job_id)[0].task_id) is None
    stopped = api.status(job.job_id, RunSettings(home=home))[0]
    assert stopped.state == FAILED and "other contents" in stopped.summary["error"]


def test_a_worker_with_other_weights_fails_its_task_instead_of_mixing(
    tmp_path: Path, poco_job: QueuedJob, monkeypatch: pytest.MonkeyPatch
) -> None:
    home, job, made = poco_job.home, poco_job.job, poco_job.made
    spec = JobSpec.model_validate(job.spec)
    (task,) = planned_tasks(home, job.job_id)
    monkeypatch.setattr(config_module, "BUILTIN_POCO_WEIGHTS_FILE", upgraded_weights(tmp_path))
    outcome = execute_task(task, spec.config, job.out, "a1-test", config_hash=made.config_hash)
    assert not outcome.ok and "install the same datagen and weights on every node" in outcome.message
    (record,) = read_failures(open_location(job.out))
    assert record.task_id == task.task_id and record.origin.endswith("objects.txt:1")
    assert read_commit(open_location(job.out), task.task_id) is None
