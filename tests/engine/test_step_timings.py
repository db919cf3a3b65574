"""Per-step task timings (`schemas.index.TASK_STEPS`), without Ray: a worker's commit record carries
them and they add up, `datagen shards stats` reports them (text and --json), the job summary that
`datagen submit` prints shows them with each step's share, and a dataset written before them says so
in one line. Timings are volatile: never in the shard, the index or the samples."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.engine import planned_tasks, queued_job
from typer.testing import CliRunner

from datagen.cli import common
from datagen.cli import jobs as jobs_cli
from datagen.cli.main import app
from datagen.engine import driver as driver_module
from datagen.engine.job_plan import JobPlan
from datagen.engine.worker import execute_task
from datagen.inspection.stats import dataset_stats
from datagen.pipeline.step_timing import NOT_RECORDED, StepClock, StepTotals, step_lines, step_totals, totals_from_json
from datagen.settings import RunSettings, ledger_for
from jobs.ledger import Job
from schemas.index import INDEX_SCHEMA, TASK_STEPS, CommitRecord
from schemas.jobs import JobSpec
from storage import ShardReader, open_dataset, open_location, read_commit

TOLERANCE = 0.05
"""Seconds the steps may exceed the task's total by (clock reads between them)."""


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, JobPlan, Path]:
    """One job of two capsule tasks (refiner none), both executed in this process; (out, plan, home)."""
    queued = queued_job(tmp_path_factory.mktemp("timed"), 'rotations = 2\nrefiner = "none"\n')
    job, home = queued.job, queued.home
    plan = JobPlan(JobSpec.model_validate(job.spec), planned_tasks(home, job.job_id))
    for task in plan.tasks:
        outcome = execute_task(task, plan.spec.config, job.out, "a1-test")
        assert outcome.ok, outcome.message
    return job.out, plan, home


def stats_output(url: str, *args: str, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setattr(common.console, "_width", 80)
    result = CliRunner().invoke(app, ["shards", "stats", url, *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result.stdout


def test_a_fresh_commit_record_times_every_step_and_they_add_up(written: tuple[str, JobPlan, Path]) -> None:
    out, plan, _ = written
    location = open_location(out)
    for task in plan.tasks:
        record = read_commit(location, task.task_id)
        assert record is not None and record.timings is not None
        timings = record.timings
        assert list(timings.steps) == list(TASK_STEPS)
        for name, seconds in timings.steps.items():
            assert seconds.cpu >= 0 and seconds.wall >= 0, name
        assert sum(s.cpu for s in timings.steps.values()) <= timings.total.cpu + TOLERANCE
        assert sum(s.wall for s in timings.steps.values()) <= timings.total.wall + TOLERANCE
        assert timings.steps["write"].wall > 0 and timings.steps["imaging"].cpu > 0
        # volatile: in the commit record only, never in the shard's attributes or the index
        attributes = ShardReader(location, record.shard).attributes
        assert "timings" not in attributes.metadata and "timings" not in attributes.model_dump()
        assert not any("timing" in field.name for field in INDEX_SCHEMA)


def test_step_clock_accumulates_and_keeps_the_step_order() -> None:
    clock = StepClock()
    for name in ("labels", "imaging", "labels"):
        with clock.step(name):
            sum(range(1000))
    timings = clock.timings()
    assert list(timings.steps) == ["imaging", "labels"]
    assert timings.total.wall >= sum(s.wall for s in timings.steps.values())


def test_stats_report_the_time_per_step(written: tuple[str, JobPlan, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    out, plan, _ = written
    stats = dataset_stats(open_dataset(out))
    assert stats.step_seconds.tasks == len(plan.tasks) and stats.step_seconds.untimed == 0
    assert list(stats.step_seconds.cpu) == list(TASK_STEPS)
    assert sum(stats.step_seconds.share(name) for name in TASK_STEPS) == pytest.approx(1.0)

    got = json.loads(stats_output(out, "--json", monkeypatch=monkeypatch))["step_seconds"]
    assert got["timed_tasks"] == len(plan.tasks) and list(got["steps"]) == list(TASK_STEPS)
    assert got["steps"]["write"]["cpu"] == pytest.approx(stats.step_seconds.cpu["write"])
    assert sum(step["share"] for step in got["steps"].values()) == pytest.approx(1.0)

    text = stats_output(out, monkeypatch=monkeypatch)
    assert f"time per step, summed over {len(plan.tasks)} tasks:" in text
    section = text.split("time per step, summed over")[1].splitlines()[1:]
    rows = {line.split()[0]: line.split() for line in section if line.startswith("  ") and line.strip()}
    for name in TASK_STEPS:
        assert name in rows and rows[name][2].endswith("%"), text
    assert NOT_RECORDED not in text


def test_a_dataset_written_before_timings_says_so_in_one_line(
    written: tuple[str, JobPlan, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, _, _ = written
    old = tmp_path / "old"
    _copy_tree(Path(out), old)
    for path in (old / "commits").glob("*.json"):
        data = json.loads(path.read_text())
        del data["timings"]  # a commit record as datagen wrote it before
        path.write_text(json.dumps(data))
        assert CommitRecord.model_validate_json(path.read_text()).timings is None
    text = stats_output(str(old), monkeypatch=monkeypatch)
    assert [line for line in text.splitlines() if "time per step" in line] == [NOT_RECORDED]
    assert json.loads(stats_output(str(old), "--json", monkeypatch=monkeypatch))["step_seconds"] is None


def test_the_job_summary_shows_cpu_seconds_per_step_and_their_shares(
    written: tuple[str, JobPlan, Path], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out, plan, home = written
    ledger = ledger_for(RunSettings(home=home))
    try:
        (job,) = ledger.jobs()
        summary = driver_module._finish(ledger, job.job_id, plan.spec, open_location(out))
    finally:
        ledger.close()
    steps = summary["step_seconds"]
    assert steps["timed_tasks"] == len(plan.tasks) and list(steps["steps"]) == list(TASK_STEPS)
    json.dumps(summary)  # the ledger keeps it as JSON
    monkeypatch.setattr(common.console, "_width", 80)
    jobs_cli._report(Job(job.job_id, "done", {}, out, 0.0, 0.0, None, summary))
    printed = capsys.readouterr().out
    assert f"time per step, summed over {len(plan.tasks)} tasks:" in printed
    for name in TASK_STEPS:
        assert f"  {name} " in printed
    assert max(len(line) for line in printed.splitlines()) <= 80


def test_totals_of_records_with_and_without_timings() -> None:
    untimed = CommitRecord(schema_version=2, task_id="t", attempt_id="a", shard="s", index_fragment="f", num_samples=1)
    totals = step_totals([untimed])
    assert totals.tasks == 0 and totals.untimed == 1
    assert step_lines(totals) == [NOT_RECORDED]


def _copy_tree(source: Path, target: Path) -> None:
    for path in source.rglob("*"):
        if path.is_file():
            destination = target / path.relative_to(source)
            destination.parent.mkdir(parents=True, exist_ok=True)
            destination.write_bytes(path.read_bytes())


def test_a_summary_read_back_with_sorted_keys_lists_the_steps_in_pipeline_order() -> None:
    """The ledger keeps the job summary as JSON that may come back key-sorted (alphabetical steps);
    the table `datagen submit` prints still follows the pipeline."""
    steps = {name: 1.0 + i for i, name in enumerate(TASK_STEPS)}
    totals = StepTotals(
        tasks=2, untimed=0, cpu=steps, wall=dict(steps), total_cpu=sum(steps.values()), total_wall=sum(steps.values())
    )
    shuffled = json.loads(json.dumps(totals.to_json(), sort_keys=True))
    back = totals_from_json(shuffled)
    assert list(back.cpu) == list(TASK_STEPS)
    assert back.cpu == steps and back.wall == steps
    names = [line.split()[0] for line in step_lines(back)[2 : 2 + len(TASK_STEPS)]]
    assert names == list(TASK_STEPS)
