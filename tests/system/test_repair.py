"""`datagen shards repair URL`, the fix every damage message names, mends what it names: on a local
dataset and on `s3://` (moto and SeaweedFS), a deleted chunk file, a truncated shard array and a
deleted commit record are each found, exactly the damaged task is re-run from the job's ledger, and
the dataset ends with the same samples as an undamaged run (every array of every shard, every
index column but the volatile ones), one attempt per task left. A sound dataset is left as it is.

One job per location (capsule and cone, 1 rotation, refiner none: seconds), damaged and repaired
in place one damage after the other (repair matches the dataset to its job by URL).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from support import storage as fx
from support.engine import (
    FAST_BUILTINS,
    assert_same_samples,
    builtin_lines,
    shard_dirs,
    start_local_ray,
    stop_local_ray,
    write_config,
    write_objects,
)
from support.s3_servers import BUCKET, S3Server
from typer.testing import CliRunner

from datagen import api
from datagen.cli.main import app
from datagen.settings import RunSettings
from jobs.ledger import DONE
from storage import Location, StorageError, committed_tasks, open_dataset, open_location, validate, validate_dataset
from storage.dataset import commit_path

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.slow,
    pytest.mark.ray,
]

RAY_CPUS = 2
AWS_VARIABLES = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_ENDPOINT_URL", "AWS_DEFAULT_REGION")


@dataclass(frozen=True)
class Made:
    url: str
    home: Path
    reference: str
    """A local copy's URL made before any damage: the samples a repair must restore."""


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("repair-inputs")
    write_config(folder / "fast.toml", rotations=1)
    write_objects(folder / "objects.txt", builtin_lines(FAST_BUILTINS))
    return folder


def make(inputs: Path, home: Path, url: str) -> str:
    job = api.submit(
        inputs / "objects.txt",
        inputs / "fast.toml",
        RunSettings(home=home, out=url, num_workers=RAY_CPUS, ray_address=None),
    )
    assert job.state == DONE, job.summary
    return job.out


@pytest.fixture(scope="module")
def reference(inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """An undamaged local dataset of the job (and the local Ray the module's jobs share)."""
    start_local_ray(RAY_CPUS)
    folder = tmp_path_factory.mktemp("repair-reference")
    yield make(inputs, folder / "home", str(folder / "dataset"))
    stop_local_ray()


@pytest.fixture(params=["local", "moto", "seaweedfs"])
def made(
    request: pytest.FixtureRequest, reference: str, inputs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Made:
    if request.param == "local":
        return Made(make(inputs, tmp_path / "home", str(tmp_path / "dataset")), tmp_path / "home", reference)
    server: S3Server = request.getfixturevalue(f"{request.param}_s3")
    for name, value in server.env().items():
        monkeypatch.setenv(name, value)
    stop_local_ray()  # Ray's workers take the store's variables when it starts
    start_local_ray(RAY_CPUS)
    url = f"s3://{BUCKET}/repair-{tmp_path.name}"
    return Made(make(inputs, tmp_path / "home", url), tmp_path / "home", reference)


# ---------------------------------------------------------------------------------------------------------
# damage, as a disk, a sync tool or a hand would do it
# ---------------------------------------------------------------------------------------------------------


def shard_file(location: Location, task_id: str) -> str:
    """The task's committed shard (one ZIP: an absolute path of its filesystem)."""
    (record,) = [r for r in committed_tasks(location) if r.task_id == task_id]
    return location.path(record.shard)


def chunk_members(data: bytes) -> list[str]:
    """The chunk members of a shard's ZIP, sorted."""
    return sorted(name for name in fx.zip_members(data) if "/c/" in name)


def delete_chunk(location: Location, task_id: str) -> None:
    path = shard_file(location, task_id)
    data = bytes(location.fs.cat_file(path))
    location.fs.pipe_file(path, fx.without_member(data, chunk_members(data)[0]))


def truncate_array(location: Location, task_id: str) -> None:
    path = shard_file(location, task_id)
    data = bytes(location.fs.cat_file(path))
    members = fx.zip_members(data)
    largest = max(chunk_members(data), key=lambda name: len(members[name]))
    location.fs.pipe_file(path, fx.with_member_cut(data, largest))


def delete_commit(location: Location, task_id: str) -> None:
    location.fs.rm(location.path(commit_path(task_id)))


DAMAGES: dict[str, Callable[[Location, str], None]] = {
    "chunk file deleted": delete_chunk,
    "shard array truncated": truncate_array,
    "commit record deleted": delete_commit,
}


def repair(runner: CliRunner, made: Made) -> str:
    result = runner.invoke(app, ["shards", "repair", made.url, "--home", str(made.home), "--workers", str(RAY_CPUS)])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result.stdout


def test_repair_mends_each_damage_to_the_undamaged_samples(runner: CliRunner, made: Made) -> None:
    location = open_location(made.url)
    samples = assert_same_samples(made.url, made.reference)
    before = {r.task_id: r.attempt_id for r in committed_tasks(location)}

    sound = repair(runner, made)
    assert "nothing to repair" in sound and "nothing was changed" in sound, sound
    assert {r.task_id: r.attempt_id for r in committed_tasks(location)} == before

    for number, (what, damage) in enumerate(DAMAGES.items()):
        task_id = sorted(before)[number % len(before)]
        damage(location, task_id)
        problems = validate(made.url, full=True)
        assert problems, f"{what}: validate saw no damage"
        if what != "commit record deleted":  # readers refuse the damaged shard and name the repair
            with pytest.raises(StorageError) as refused:
                dataset = open_dataset(made.url)
                for index in range(len(dataset)):
                    dataset[index]
            assert f"datagen shards repair {made.url}" in str(refused.value), str(refused.value)
        output = repair(runner, made)
        assert f"re-ran {task_id}" in output, (what, output)
        assert output.count("re-ran ") == 1, (what, output)  # exactly the damaged task
        assert validate(made.url, full=True) == [], what
        assert assert_same_samples(made.url, made.reference) == samples, what
        after = {r.task_id: r.attempt_id for r in committed_tasks(location)}
        assert after[task_id] != before[task_id], f"{what}: the damaged task was not re-run"
        assert {t: a for t, a in after.items() if t != task_id} == {t: a for t, a in before.items() if t != task_id}
        assert sorted(shard_dirs(made.url)[task_id]) == sorted(
            f"{after[task_id]}.{kind}" for kind in ("parquet", "zarr.zip")
        ), f"{what}: the damaged attempt's files were not swept"
        before = after


def test_repair_reads_the_records_not_the_messages(
    runner: CliRunner, reference: str, inputs: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every validation message reworded (and every line with it): repair still finds and re-runs exactly
    the damaged task, from the problems' records."""
    import dataclasses

    from datagen.engine import repair as engine_repair

    def reworded(*args: object, **kwargs: object) -> object:
        found = validate_dataset(*args, **kwargs)  # type: ignore[arg-type]
        problems = [dataclasses.replace(p, message=f"something else #{n}") for n, p in enumerate(found.problems)]
        return dataclasses.replace(found, problems=problems)

    monkeypatch.setattr(engine_repair, "validate_dataset", reworded)
    made = Made(make(inputs, tmp_path / "home", str(tmp_path / "dataset")), tmp_path / "home", reference)
    location = open_location(made.url)
    task_id = sorted(r.task_id for r in committed_tasks(location))[0]
    truncate_array(location, task_id)
    output = repair(runner, made)
    assert f"re-ran {task_id}: " in output and "something else #" in output and output.count("re-ran ") == 1
    assert validate(made.url, full=True) == []
    assert assert_same_samples(made.url, made.reference) > 0


def test_a_moved_dataset_is_repaired_from_the_jobs_of_its_identity(
    runner: CliRunner, reference: str, inputs: Path, tmp_path: Path
) -> None:
    """A dataset copied elsewhere (the usual case after shipping) is found by its dataset.json's config,
    not its path: its damaged task is re-run into the copy, the original is not touched; a ledger that
    made no dataset of this config says in one line what repair needs (issue 52, finding 4)."""
    import shutil

    made = Made(make(inputs, tmp_path / "home", str(tmp_path / "dataset")), tmp_path / "home", reference)
    moved = tmp_path / "shipped" / "copy"
    shutil.copytree(made.url, moved)
    location = open_location(str(moved))
    task_id = sorted(r.task_id for r in committed_tasks(location))[0]
    truncate_array(location, task_id)
    original = {r.task_id: r.attempt_id for r in committed_tasks(open_location(made.url))}
    output = repair(runner, Made(str(moved), made.home, reference))
    assert f"re-ran {task_id}" in output and output.count("re-ran ") == 1, output
    assert validate(str(moved), full=True) == []
    assert assert_same_samples(str(moved), reference) == assert_same_samples(made.url, reference)
    assert {r.task_id: r.attempt_id for r in committed_tasks(open_location(made.url))} == original
    truncate_array(location, task_id)
    result = runner.invoke(app, ["shards", "repair", str(moved), "--home", str(tmp_path / "elsewhere")])
    assert result.exit_code == 2
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith(f"error: {moved}: needs task {task_id} run again") and "give --home the ledger" in line
