"""Mistakes caught when a job is planned, and forgotten once fixed (issue 52, findings 1-3).

- A submit onto a dataset of another config is refused in one line and leaves nothing in the ledger:
  no failed job with pending tasks shown against the dataset it protected (finding 1).
- A missing mesh file is named when the job is planned, before any task runs, also with --detach;
  --strict refuses the whole job instead (finding 2).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli.main import app
from datagen.engine import driver as driver_module
from datagen.engine.driver import dataset_info
from datagen.settings import RunSettings
from schemas.config import GenerationConfig
from storage import init_dataset, open_location, read_info


@pytest.fixture
def no_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object) -> None:
        raise AssertionError("Ray was started for a job that should have been refused")

    monkeypatch.setattr(driver_module, "ensure_ray", refuse)
    monkeypatch.setattr(common.console, "_width", 400)
    monkeypatch.setattr(common.error_console, "_width", 400)


def objects_file(folder: Path, *lines: str) -> Path:
    path = folder / "objects.txt"
    path.write_text("".join(f"{line}\n" for line in lines))
    return path


@pytest.mark.parametrize("detach", [False, True])
def test_a_dataset_of_another_config_is_refused_before_the_job_is_recorded(
    detach: bool, tmp_path: Path, no_ray: None
) -> None:
    taken = tmp_path / "taken"
    made = init_dataset(open_location(str(taken)), dataset_info(GenerationConfig(rotations=3, refiner="none")))
    config = tmp_path / "one.toml"
    config.write_text('rotations = 1\nrefiner = "none"\n')
    home = tmp_path / "home"
    objects = objects_file(tmp_path, "builtin:capsule")
    args = ["submit", "--objects", str(objects), "--config", str(config), "--out", str(taken), "--home", str(home)]
    result = CliRunner().invoke(app, args + (["--detach"] if detach else []))
    assert result.exit_code == common.EXIT_USER_ERROR, result.output
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: {taken}: holds a dataset of another config") and "write to a new --out" in line
    assert api.status(None, RunSettings(home=home)) == []  # no job: nothing to resume, nothing shown against it
    assert read_info(open_location(str(taken))).config_hash == made.config_hash


def test_a_missing_mesh_is_named_at_plan_time_and_the_rest_is_queued(tmp_path: Path, no_ray: None) -> None:
    home = tmp_path / "home"
    objects = objects_file(tmp_path, "builtin:capsule", "missing.obj", "builtin:cone")
    config = tmp_path / "one.toml"
    config.write_text('rotations = 1\nrefiner = "none"\n')
    args = ["submit", "--objects", str(objects), "--config", str(config), "--home", str(home), "--detach"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    (line,) = [line for line in result.stderr.splitlines() if "missing.obj" in line]
    assert line.startswith(f"skipped {objects}:2: mesh file not found: ") and "fix the path" in line
    assert "queued" in result.stdout
    (job,) = api.status(None, RunSettings(home=home))
    ledger = api.ledger_for(RunSettings(home=home))
    try:
        assert sum(ledger.task_counts(job.job_id).values()) == 2  # capsule and cone
    finally:
        ledger.close()


def test_strict_refuses_a_job_with_a_bad_line_before_recording_it(tmp_path: Path, no_ray: None) -> None:
    home = tmp_path / "home"
    objects = objects_file(tmp_path, "builtin:capsule", "missing.obj", "also-missing.obj")
    args = ["submit", "--objects", str(objects), "--home", str(home), "--detach", "--strict"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == common.EXIT_USER_ERROR
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"error: {objects}:2: mesh file not found") and "(and 1 more)" in line
    assert "submit without --strict" in line
    assert api.status(None, RunSettings(home=home)) == []


def test_status_says_why_a_job_failed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    home = tmp_path / "home"
    settings = RunSettings(home=home, out=str(tmp_path / "out"))
    objects = objects_file(tmp_path, "builtin:capsule", "missing.obj")
    job = api.enqueue(objects, GenerationConfig(rotations=1, refiner="none"), settings)
    line_error = f"{objects}:2: mesh file not found: {tmp_path / 'missing.obj'}; fix the path"
    summary = {"tasks": 1, "done": 1, "failed": 0, "refused_lines": 1, "line_errors": [line_error], "failures": []}
    ledger = api.ledger_for(settings)
    try:
        ledger.start_job(job.job_id, "driver", lease=60)
        for claim in ledger.claim(job.job_id, "driver", 60):
            ledger.complete(job.job_id, claim.task.task_id, claim.attempt_id, samples=3, placement=None)
        ledger.finish_job(job.job_id, summary, other_failures=1)
    finally:
        ledger.close()
    monkeypatch.setattr(common.console, "_width", 400)
    result = CliRunner().invoke(app, ["status", "--home", str(home)])
    assert result.exit_code == 0, result.output
    assert f"job {job.job_id} failed: 1 objects-file line named no usable object (first: {line_error})" in result.stdout


@pytest.mark.slow
@pytest.mark.ray
def test_a_line_fixed_and_submitted_again_is_no_longer_reported_missing(tmp_path: Path) -> None:
    """Finding 3: the failure record of a bad line belongs to that submission; the same objects file
    submitted again, the line fixed, retires it, so ls, stats and validate report nothing missing. A
    record of another objects file's line is left alone."""
    import trimesh
    from support.engine import start_local_ray, stop_local_ray

    from schemas.index import failure_record
    from storage import open_dataset, read_failures, validate
    from storage.dataset import line_failure_id, write_failure

    home, out = tmp_path / "home", tmp_path / "out"
    config = tmp_path / "one.toml"
    config.write_text('rotations = 1\nrefiner = "none"\n')
    objects = objects_file(tmp_path, "builtin:capsule", "box.obj")
    settings = RunSettings(home=home, out=str(out), num_workers=1)
    start_local_ray(1)
    try:
        first = api.submit(objects, config, settings)
        assert first.state == "failed" and first.summary["refused_lines"] == 1
        (record,) = read_failures(open_location(str(out)))
        assert record.origin == f"{objects}:2" and record.task_id == line_failure_id(f"{objects}:2")
        other = f"{tmp_path / 'other.txt'}:7"
        write_failure(open_location(str(out)), failure_record(line_failure_id(other), "not found", origin=other))
        trimesh.creation.box(extents=(0.08, 0.06, 0.04)).export(tmp_path / "box.obj")  # the line fixed
        second = api.submit(objects, config, settings)
    finally:
        stop_local_ray()
    assert second.state == "done", second.summary
    assert [r.origin for r in read_failures(open_location(str(out)))] == [other]
    dataset = open_dataset(str(out))
    assert [f.origin for f in dataset.failures()] == [other]
    assert not [p for p in validate(str(out), full=False) if "box.obj" in str(p)]
