"""The engine end to end on a real local Ray (datagen/engine/driver.py, datagen/api.py, the jobs CLI): built-ins
and shared meshes give sound datasets holding exactly the planned samples, the same job gives the same
samples on 1 and on 2 worker CPUs, and bad input is written down by line while the good objects go on.

One private Ray (2 CPUs) serves the whole module (in-process API and CLI calls reuse it); the 1-CPU
run of the determinism test is a `datagen submit --workers 1` subprocess with its own Ray.
"""

from __future__ import annotations

import os
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from support.engine import (
    FAST_BUILTINS,
    SHARED_MESH_LINES,
    assert_same_samples,
    builtin_lines,
    check_complete_dataset,
    datagen_processes,
    job_tasks,
    only_job,
    planned_task_ids,
    shard_dirs,
    start_local_ray,
    stop_local_ray,
    summarize,
    write_config,
    write_objects,
)
from support.meshes import SHARED_MESHES
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli.main import app
from datagen.config_io import load_config
from datagen.errors import ConfigError
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.task import run_task
from datagen.pipeline.viewspace import build_view_space
from datagen.settings import RunSettings
from jobs.ledger import DONE, FAILED
from storage import open_dataset, open_location, read_commit, read_failures, validate

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.ray,
]

RAY_CPUS = 2


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    start_local_ray(RAY_CPUS)
    yield
    stop_local_ray()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    write_config(folder / "fast.toml", rotations=2)
    write_config(folder / "one.toml", rotations=1)
    write_objects(folder / "builtins.txt", builtin_lines(FAST_BUILTINS))
    return folder


def settings_for(home: Path) -> RunSettings:
    return RunSettings(home=home, num_workers=RAY_CPUS, ray_address=None)


@pytest.fixture(scope="module")
def builtin_job(inputs: Path, tmp_path_factory):
    """2 built-ins x 2 rotations through the Python API on the module's 2-CPU Ray."""
    home = tmp_path_factory.mktemp("builtin-home")
    job = api.submit(inputs / "builtins.txt", inputs / "fast.toml", settings_for(home))
    return home, job


# ---------------------------------------------------------------------------------------------------------
# end to end
# ---------------------------------------------------------------------------------------------------------


def test_builtins_end_to_end(builtin_job) -> None:
    import ray

    assert ray.cluster_resources()["CPU"] == RAY_CPUS
    home, job = builtin_job
    assert job.state == DONE, job.summary
    assert Path(job.out) == home / "datasets" / job.job_id
    task_ids = planned_task_ids(home, job.job_id)
    assert len(task_ids) == len(FAST_BUILTINS) * 2
    summary = check_complete_dataset(job.out, task_ids)
    assert job.summary is not None
    assert job.summary["samples"] == summary.samples
    assert (job.summary["tasks"], job.summary["done"], job.summary["failed"]) == (4, 4, 0)
    tasks = job_tasks(home, job.job_id)
    assert [t.task_id for t in tasks] == task_ids
    per_task = Counter(open_dataset(job.out).index.column("task_id").to_pylist())
    for task in tasks:
        assert (task.state, task.attempts, task.error) == (DONE, 1, None)
        # the commit names an execution of the ledger's (only) attempt, with the ledger's sample count
        assert summary.commits[task.task_id].startswith(f"{task.attempt_id}-")
        assert task.samples == per_task[task.task_id]
        assert task.placement and "@" in task.placement
    assert sum(t.samples or 0 for t in tasks) == summary.samples
    # one execution per task: one shard group and one index fragment each, nothing else
    assert all(len(files) == 2 for files in shard_dirs(job.out).values())
    assert read_failures(open_location(job.out)) == []
    # the finalised index covers every commit (readers need not merge fragments)
    assert open_location(job.out).exists("index/manifest.json")


def test_builtins_hold_exactly_the_planned_cases(builtin_job, inputs: Path) -> None:
    """Independent of the engine: the pipeline run in this process plans the same cases per task
    (cases minus dropped empties = samples) and gives the same sample ids."""
    _, job = builtin_job
    config = load_config(inputs / "fast.toml")
    view_space = build_view_space(config.view_space)
    dataset = open_dataset(job.out)
    task_of_sample = dict(
        zip(dataset.index.column("sample_id").to_pylist(), dataset.index.column("task_id").to_pylist(), strict=True)
    )
    planned = 0
    for spec in read_objects_file(inputs / "builtins.txt").objects:
        prepared = prepare_object(spec, config)
        for rotation in range(config.rotations):
            result = run_task(prepared, rotation, config, view_space, make_refiner(config))
            assert len(result.cases) - result.dropped_empty == len(result.samples)
            planned += len(result.samples)
            ids = sorted(s.sample_id for s in result.samples)
            assert ids == sorted(s for s, t in task_of_sample.items() if t == result.task_id)
    assert len(dataset) == planned == summarize(job.out).planned


@pytest.mark.slow
def test_shared_meshes_end_to_end(inputs: Path, tmp_path: Path) -> None:
    missing = [line.split()[0] for line in SHARED_MESH_LINES if not (SHARED_MESHES / line.split()[0]).is_file()]
    if missing:
        pytest.skip(f"shared meshes {missing} not found in {SHARED_MESHES}")
    objects = write_objects(tmp_path / "meshes.txt", [f"{SHARED_MESHES / line}" for line in SHARED_MESH_LINES])
    job = api.submit(objects, inputs / "one.toml", settings_for(tmp_path / "home"))
    assert job.state == DONE, job.summary
    task_ids = planned_task_ids(tmp_path / "home", job.job_id)
    assert len(task_ids) == 3
    summary = check_complete_dataset(job.out, task_ids)
    assert job.summary is not None and job.summary["samples"] == summary.samples
    names = set(open_dataset(job.out).index.column("object_name").to_pylist())
    assert names == {"cow", "teapot", "spot"}
    assert all(t.attempts == 1 and t.state == DONE for t in job_tasks(tmp_path / "home", job.job_id))


def test_a_finished_job_removes_leftovers_of_interrupted_attempts(inputs: Path, tmp_path: Path) -> None:
    """What a killed or disk-starved attempt of the job's tasks left (an uncommitted attempt, files
    of writes that never published) is removed once the job is complete, and the report says so;
    another job's attempt and a temporary file still being written stay."""
    out = tmp_path / "out"
    objects = write_objects(tmp_path / "one.txt", builtin_lines(("capsule",)))
    home = tmp_path / "home"
    job = api.enqueue(objects, inputs / "one.toml", RunSettings(home=home, out=str(out)))
    (task_id,) = planned_task_ids(home, job.job_id)
    stale = [
        f"shards/{task_id}/a1-0badc0ffee00-00000000.zarr/zarr.json",
        f"shards/{task_id}/a1-0badc0ffee00-00000001.zarr.zip.tmp-0123456789abcdef",
        f"shards/{task_id}/a1-0badc0ffee00-00000000.parquet",
        f"commits/{task_id}.json.tmp-0123456789abcdef",
        "index.parquet.tmp-0123456789abcdef",
    ]
    kept = ["shards/other-job-task/a1-000000000000-00000000.parquet", f"failures/{task_id}.json.tmp-fedcba9876543210"]
    for relative in stale + kept:
        (out / relative).parent.mkdir(parents=True, exist_ok=True)
        (out / relative).write_bytes(b"partial")
    an_hour_ago = time.time() - 3600
    for relative in stale:
        os.utime(out / relative, (an_hour_ago, an_hour_ago))
    original = (common.console._width, common.error_console._width)
    common.console._width = common.error_console._width = 400
    try:
        result = CliRunner().invoke(app, ["resume", job.job_id, "--home", str(home), "--workers", "2"])
    finally:
        common.console._width, common.error_console._width = original
    assert result.exit_code == 0, result.output
    assert all(not (out / relative).exists() for relative in stale)
    assert all((out / relative).exists() for relative in kept)
    assert f"removed 5 leftover files of interrupted attempts (commits/{task_id}.json.tmp-" in result.stdout
    assert shard_dirs(str(out))[task_id] == sorted(Path(p).name for p in _committed_files(str(out), task_id))
    done = only_job(home)
    assert done is not None and done.summary is not None and done.summary["swept"] == 5
    check_complete_dataset(str(out), [task_id])


def _committed_files(url: str, task_id: str) -> list[str]:
    record = read_commit(open_location(url), task_id)
    assert record is not None
    return [record.index_fragment, record.shard]


# ---------------------------------------------------------------------------------------------------------
# determinism across worker counts
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_one_and_two_worker_cpus_give_identical_samples(builtin_job, inputs: Path, tmp_path: Path) -> None:
    """The 2-CPU run is `builtin_job` (this module's Ray); the 1-CPU run a `datagen submit --workers 1`."""
    home2, job2 = builtin_job
    home1 = tmp_path / "home1"
    out1 = tmp_path / "out1"
    args = ["submit", "--objects", str(inputs / "builtins.txt"), "--config", str(inputs / "fast.toml")]
    args += ["--workers", "1", "--home", str(home1), "--out", str(out1)]
    with datagen_processes() as start:
        process = start(args, tmp_path / "submit1.log")
        assert process.wait(timeout=240) == 0, process.output()
    job1 = only_job(home1)
    assert job1 is not None and job1.state == DONE
    assert planned_task_ids(home1, job1.job_id) == planned_task_ids(home2, job2.job_id)
    assert validate(str(out1), full=True) == []
    compared = assert_same_samples(str(out1), job2.out)
    assert compared == summarize(job2.out).samples > 0


# ---------------------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bad_input_run(inputs: Path, tmp_path_factory):
    """capsule, a missing file, a corrupt mesh, cone: `datagen submit` in this process (module Ray)."""
    folder = tmp_path_factory.mktemp("bad-input")
    (folder / "bad.obj").write_bytes(bytes(range(256)) * 12 + b"\x00garbage\xff" * 50)
    lines = ["builtin:capsule", str(folder / "missing.obj"), str(folder / "bad.obj"), "builtin:cone"]
    objects = write_objects(folder / "objects.txt", lines)
    text = objects.read_text().splitlines()
    line_of = {
        name: text.index(line) + 1 for name, line in zip(("capsule", "missing", "bad", "cone"), lines, strict=True)
    }
    home = folder / "home"
    original = (common.console._width, common.error_console._width)
    common.console._width = common.error_console._width = 400  # no wrapping inside FILE:LINE
    try:
        result = CliRunner().invoke(
            app,
            ["submit", "--objects", str(objects), "--config", str(inputs / "fast.toml"), "--home", str(home)],
        )
    finally:
        common.console._width, common.error_console._width = original
    job = only_job(home)
    return objects, line_of, result, job, home


def test_bad_input_good_objects_written_failures_recorded(bad_input_run) -> None:
    objects, line_of, result, job, home = bad_input_run
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    assert job is not None and job.state == FAILED
    # the good objects: every planned task of capsule and cone, complete and sound
    tasks = job_tasks(home, job.job_id)
    done = [t.task_id for t in tasks if t.state == DONE]
    failed = [t for t in tasks if t.state == FAILED]
    assert sorted({t.spec["object"]["name"] for t in tasks if t.state == DONE}) == ["capsule", "cone"]
    assert len(done) == 4
    check_complete_dataset(job.out, done)
    # the corrupt mesh: both rotations failed with a message; the missing file never became a task
    assert len(failed) == 2 and {t.spec["object"]["name"] for t in failed} == {"bad"}
    assert all(t.error for t in failed)
    assert len(tasks) == 6
    assert len(job.spec["line_errors"]) == 1 and f"{objects}:{line_of['missing']}" in job.spec["line_errors"][0]
    # the dataset itself says what is missing and why, by objects-file line
    failures = open_dataset(job.out).failures()
    origins = sorted(f.origin for f in failures)
    assert origins == sorted([f"{objects}:{line_of['missing']}"] + [f"{objects}:{line_of['bad']}"] * 2)
    by_origin = {f.origin: f.message for f in failures}
    assert "not found" in by_origin[f"{objects}:{line_of['missing']}"]
    assert "bad.obj" in by_origin[f"{objects}:{line_of['bad']}"]
    assert job.summary is not None and job.summary["done"] == 4
    assert (job.summary["failed"], job.summary["refused_lines"]) == (2, 1)  # tasks apart from lines


def test_bad_input_cli_names_the_missing_file_by_line(bad_input_run) -> None:
    objects, line_of, result, _, _ = bad_input_run
    assert f"{objects}:{line_of['missing']}" in result.output, result.output


def test_bad_input_cli_names_the_corrupt_mesh_by_line(bad_input_run) -> None:
    objects, line_of, result, _, _ = bad_input_run
    assert f"{objects}:{line_of['bad']}" in result.output, result.output


@pytest.mark.slow
def test_poco_refiner_one_and_two_worker_cpus_give_identical_samples(inputs: Path, tmp_path: Path) -> None:
    """The default refiner (poco, shipped weights) through the engine: 2 tasks on the module's 2-CPU
    Ray, then the same job by `datagen submit --workers 1`; every array and index row identical."""
    config = write_config(tmp_path / "poco.toml", rotations=2, refiner="poco")
    objects = write_objects(tmp_path / "one.txt", builtin_lines(("capsule",)))
    job2 = api.submit(objects, config, settings_for(tmp_path / "home2"))
    assert job2.state == DONE, job2.summary
    home1, out1 = tmp_path / "home1", tmp_path / "out1"
    args = ["submit", "--objects", str(objects), "--config", str(config), "--workers", "1"]
    args += ["--home", str(home1), "--out", str(out1)]
    with datagen_processes() as start:
        process = start(args, tmp_path / "submit1.log")
        assert process.wait(timeout=400) == 0, process.output()
    job1 = only_job(home1)
    assert job1 is not None and job1.state == DONE
    assert validate(str(out1), full=True) == []
    assert open_dataset(str(out1)).info.config.refiner == "poco"
    compared = assert_same_samples(str(out1), job2.out)
    assert compared == summarize(job2.out).samples > 0
    # poco added keys beyond the observation in at least one sample
    dataset = open_dataset(job2.out)
    assert any(len(dataset.keys(i, "points")) > len(dataset.keys(i, "observed")) for i in range(len(dataset)))


def test_a_version_1_dataset_keeps_its_layout_when_a_job_adds_tasks(inputs: Path, tmp_path: Path) -> None:
    """A dataset made before schema version 2 (no minimum covers) that a job of this version writes into
    gets its new tasks in version 1 too, so readers never meet two layouts in one dataset."""
    from datagen.engine.driver import dataset_info
    from storage import init_dataset

    out = tmp_path / "made-by-version-1"
    old = dataset_info(load_config(inputs / "one.toml")).model_copy(update={"schema_version": 1})
    init_dataset(open_location(str(out)), old)
    settings = RunSettings(home=tmp_path / "home", num_workers=RAY_CPUS, ray_address=None, out=str(out))
    job = api.submit(inputs / "builtins.txt", inputs / "one.toml", settings)
    assert job.state == DONE
    dataset = open_dataset(str(out))
    assert dataset.info.schema_version == 1 and not dataset.has_ambiguity
    assert set(dataset.index.column("schema_version").to_pylist()) == {1}
    assert validate(str(out), full=True) == []


def test_refiner_gpus_without_a_gpu_is_one_clear_error(inputs: Path, tmp_path: Path) -> None:
    import ray

    if ray.cluster_resources().get("GPU", 0):
        pytest.skip("this machine's Ray has a GPU")
    settings = RunSettings(home=tmp_path / "home", num_workers=RAY_CPUS, ray_address=None, refiner_gpus=0.5)
    with pytest.raises(ConfigError, match="no GPU; drop --refiner-gpus"):
        api.submit(inputs / "builtins.txt", inputs / "one.toml", settings)
    job = only_job(tmp_path / "home")
    assert job is not None and job.state == FAILED and "no GPU" in job.summary["error"]


def test_a_flat_mesh_is_made_and_named_once_in_the_jobs_warnings(inputs: Path, tmp_path: Path) -> None:
    """A zero-thickness sheet is a valid mesh, but every view sees nearly all of it: the job makes it
    and its summary names it once (not once per rotation), by objects-file line (issue 42)."""
    sheet = tmp_path / "sheet.obj"
    sheet.write_text("v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n")
    objects = write_objects(tmp_path / "objects.txt", [str(sheet), "builtin:capsule"])
    job = api.submit(objects, inputs / "fast.toml", settings_for(tmp_path / "home"))
    assert job.state == DONE and job.summary["done"] == 4
    (warning,) = job.summary["warnings"]
    assert warning.startswith(f"{objects}:2: sheet: flat (thinnest extent 0.00% of its size)")  # after a comment
