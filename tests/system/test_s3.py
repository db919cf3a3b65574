"""Datasets on `s3://` against S3 HTTP servers on loopback, each in turn: moto's standalone server and
SeaweedFS, a real store (both authenticated; `support.s3_servers`, started once per session): a
job writes through s3fs and reads back with
`storage.open_dataset` and the PyTorch Dataset; a run killed while a shard is half written and then
resumed ends with exactly the planned samples, readers never seeing the half shard; refused
credentials and an unreachable endpoint fail the job with one error line in bounded time; and no
secret is written anywhere.

The credentials are real keys the server checks (moto: an IAM user created through its first
unauthenticated calls; SeaweedFS: its identities file); every request is signed and checked. They reach the
driver, the Ray workers and every `datagen` subprocess the usual way: AWS_* environment variables.
"""

from __future__ import annotations

import signal
import socket
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from support.engine import (
    SIX_BUILTINS,
    DatasetSummary,
    assert_same_samples,
    builtin_lines,
    check_complete_dataset,
    datagen_processes,
    done_count,
    job_tasks,
    kill_exact,
    only_job,
    planned_task_ids,
    ray_task_workers,
    run_datagen,
    shard_dirs,
    start_local_ray,
    stop_local_ray,
    submit_args,
    summarize,
    wait_until,
    write_config,
    write_objects,
)
from support.s3_servers import BUCKET, REGION, S3Server, unused_port

from datagen import api
from datagen.settings import RunSettings
from jobs.ledger import DONE, PENDING, RUNNING, Job, Task
from schemas.index import CommitRecord
from storage import committed_tasks, open_dataset, open_location, validate
from storage.dataset import sweep_orphans

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.slow,
    pytest.mark.ray,
    pytest.mark.s3,
]

RAY_CPUS = 2
OBJECTS = SIX_BUILTINS[:3]
"""capsule, cone, torus: at 2 rotations, 6 tasks, enough for a kill to land between two of them."""
TASKS = len(OBJECTS) * 2
NUM_POINTS = 256
FAILURE_BOUND = 120.0
"""Seconds a failing `datagen submit` may take before the test calls it a hang."""
WRONG_SECRET = f"wrong-secret-{uuid.uuid4().hex}"


@pytest.fixture(scope="module")
def s3_server(s3_store: S3Server) -> S3Server:
    """Each store in turn (moto, then SeaweedFS: `tests/conftest.py`); authentication is on: an
    unknown key is refused."""
    import botocore.exceptions

    with pytest.raises(botocore.exceptions.ClientError):
        s3_store.client("AKIAUNKNOWN000000000", "not-a-secret").list_objects_v2(Bucket=BUCKET)
    return s3_store


@pytest.fixture(scope="module")
def aws_env(s3_server: S3Server) -> Iterator[S3Server]:
    """The standard AWS variables for this process, its Ray workers and its subprocesses."""
    import s3fs

    with pytest.MonkeyPatch.context() as patch:
        for name in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_REGION", "AWS_SESSION_TOKEN"):
            patch.delenv(name, raising=False)
        for name in ("DATAGEN_STORAGE_TIMEOUT", "DATAGEN_STORAGE_RETRIES"):
            patch.delenv(name, raising=False)
        patch.setenv("AWS_ACCESS_KEY_ID", s3_server.key_id)
        patch.setenv("AWS_SECRET_ACCESS_KEY", s3_server.secret)
        patch.setenv("AWS_ENDPOINT_URL", s3_server.endpoint)
        patch.setenv("AWS_DEFAULT_REGION", REGION)
        yield s3_server
    s3fs.S3FileSystem.clear_instance_cache()  # no client of this server outlives the module


@pytest.fixture(scope="module")
def local_ray(aws_env: S3Server) -> Iterator[None]:
    """Started after the AWS variables are set, so its workers inherit them."""
    start_local_ray(RAY_CPUS)
    yield
    stop_local_ray()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    write_config(folder / "fast.toml", rotations=2)
    write_objects(folder / "objects.txt", builtin_lines(OBJECTS))
    return folder


@dataclass(frozen=True)
class Reference:
    home: Path
    job: Job
    summary: DatasetSummary


@pytest.fixture(scope="module")
def reference(aws_env: S3Server, local_ray: None, inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> Reference:
    """3 built-ins x 2 rotations through `datagen.api.submit` to s3://datasets/reference."""
    home = tmp_path_factory.mktemp("reference")
    settings = RunSettings(home=home, out=f"s3://{BUCKET}/reference", num_workers=RAY_CPUS, ray_address=None)
    job = api.submit(inputs / "objects.txt", inputs / "fast.toml", settings)
    assert job.state == DONE, job.summary
    assert len(planned_task_ids(home, job.job_id)) == TASKS
    return Reference(home, job, summarize(job.out))


# ---------------------------------------------------------------------------------------------------------
# (a) submit to s3://, read back
# ---------------------------------------------------------------------------------------------------------


def test_submit_to_s3_and_read_back(reference: Reference, aws_env: S3Server) -> None:
    from storage.torch import OSVPDataset

    job = reference.job
    assert job.out == f"s3://{BUCKET}/reference"
    # validate(full=True) clean, exactly the planned samples of every task, no sample id twice
    summary = check_complete_dataset(job.out, planned_task_ids(reference.home, job.job_id))
    assert summary == reference.summary
    assert job.summary is not None and job.summary["samples"] == summary.samples
    # the objects are in the bucket (not in some local folder named like the URL)
    keys = aws_env.keys("reference/")
    assert "reference/dataset.json" in keys and "reference/index/manifest.json" in keys
    assert sorted(k for k in keys if k.startswith("reference/commits/")) == sorted(
        f"reference/commits/{task_id}.json" for task_id in summary.commits
    )
    dataset = open_dataset(job.out)
    assert len(dataset) == summary.samples
    assert dataset.url == job.out
    torch_dataset = OSVPDataset(job.out, num_points=NUM_POINTS)
    assert len(torch_dataset) == summary.samples
    for index in sorted({0, len(torch_dataset) // 2, len(torch_dataset) - 1}):
        item = torch_dataset[index]
        assert tuple(item["points"].shape) == (NUM_POINTS, 3)
        assert tuple(item["view_state"].shape) == tuple(item["label"].shape) == (dataset.num_views,)
        view_state, label = dataset.masks(index)  # the bits of the stored masks, as 0/1 floats
        assert item["label"].tolist() == [float((int(label) >> bit) & 1) for bit in range(dataset.num_views)]
        assert item["view_state"].tolist() == [float((int(view_state) >> bit) & 1) for bit in range(dataset.num_views)]
        assert int(item["index"]) == index


# ---------------------------------------------------------------------------------------------------------
# (b) a run killed with a half-written shard in the bucket, resumed to the same prefix
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KilledAndResumed:
    home: Path
    url: str
    job_id: str
    before: dict[str, Task]
    """Ledger tasks right after the kill."""
    commits_before: dict[str, CommitRecord]
    half: dict[str, list[str]]
    """task id -> attempt files in the bucket without a commit record, right after the kill."""
    reader_before: tuple[list[str], int]
    """What a reader saw after the kill: sorted distinct shards of its index, and its length."""
    problems_before: list[str]
    outputs: list[str]


def uncommitted_files(server: S3Server, prefix: str) -> dict[str, list[str]]:
    """task id -> attempt files/folders under shards/<task>/ of tasks that have no commit record."""
    keys = server.keys(f"{prefix}/")
    committed = {k.rsplit("/", 1)[1].removesuffix(".json") for k in keys if k.startswith(f"{prefix}/commits/")}
    found: dict[str, set[str]] = {}
    for key in keys:
        parts = key[len(prefix) + 1 :].split("/")
        if parts[0] == "shards" and len(parts) >= 3 and parts[1] not in committed:
            found.setdefault(parts[1], set()).add(parts[2])
    return {task: sorted(names) for task, names in sorted(found.items())}


@pytest.fixture(scope="module")
def killed_and_resumed(
    reference: Reference, aws_env: S3Server, inputs: Path, tmp_path_factory: pytest.TempPathFactory
) -> KilledAndResumed:
    """`datagen submit --out s3://datasets/resumed` (1 worker) SIGKILLed, with its Ray, while a task
    worker (frozen with SIGSTOP) has written part of an attempt but not its commit; then `datagen
    resume`."""
    stop_local_ray()  # give this process's Ray CPUs back; the subprocesses start their own
    folder = tmp_path_factory.mktemp("resumed")
    home = folder / "home"
    url = f"s3://{BUCKET}/resumed"
    with datagen_processes() as start:
        driver = start([*submit_args(inputs, url, home), "--workers", "1"], folder / "submit.log")
        frozen: list[Any] = []

        def frozen_mid_write() -> bool:
            """At least one task done and a task worker stopped while its attempt is half written."""
            assert driver.poll() is None, f"the driver ended before the kill:\n{driver.output()}"
            if done_count(home) < 1:
                return False
            busy = ray_task_workers(driver.pid)
            if not busy:
                return False
            kill_exact(busy, signal.SIGSTOP)
            time.sleep(0.1)  # requests already sent land before the bucket is listed
            if uncommitted_files(aws_env, "resumed"):
                frozen.extend(busy)
                return True
            kill_exact(busy, signal.SIGCONT)
            return False

        wait_until(frozen_mid_write, timeout=240, interval=0.02, what="a task worker in the middle of a write")
        kill_exact(frozen, signal.SIGKILL)
        driver.sigkill()
        submit_output = driver.output()
        driver.close()  # the dead driver's Ray
        job = only_job(home)
        assert job is not None
        before = {t.task_id: t for t in job_tasks(home, job.job_id)}
        location = open_location(url)
        commits_before = {r.task_id: r for r in committed_tasks(location)}
        half = uncommitted_files(aws_env, "resumed")
        reader = open_dataset(url)
        reader_before = (sorted(set(reader.index.column("shard").to_pylist())), len(reader))
        problems_before = validate(url, full=True)

        resume = start(["resume", job.job_id, "--home", str(home), "--workers", str(RAY_CPUS)], folder / "resume.log")
        assert resume.wait(timeout=300) == 0, resume.output()
        outputs = [submit_output, resume.output()]
    return KilledAndResumed(
        home, url, job.job_id, before, commits_before, half, reader_before, problems_before, outputs
    )


def test_killed_run_left_a_half_shard_readers_ignore(killed_and_resumed: KilledAndResumed) -> None:
    run = killed_and_resumed
    done_before = {task_id for task_id, t in run.before.items() if t.state == DONE}
    assert 1 <= len(done_before) < TASKS, "the kill did not land mid-job"
    assert done_before <= set(run.commits_before)
    assert run.half, "no half-written attempt in the bucket after the kill"
    assert not set(run.half) & set(run.commits_before)
    # the reader of the killed run's dataset saw exactly the committed shards, nothing half written
    shards, samples = run.reader_before
    assert shards == sorted(r.shard for r in run.commits_before.values())
    assert samples == sum(r.num_samples for r in run.commits_before.values())
    assert run.problems_before == []


def test_resumed_run_has_exactly_the_planned_samples(
    killed_and_resumed: KilledAndResumed, reference: Reference, aws_env: S3Server
) -> None:
    run = killed_and_resumed
    job = only_job(run.home)
    assert job is not None and job.job_id == run.job_id
    assert job.state == DONE, job.summary
    after = {t.task_id: t for t in job_tasks(run.home, run.job_id)}
    assert all(t.state == DONE for t in after.values())
    summary = check_complete_dataset(run.url, list(reference.summary.commits))
    assert summary.samples == reference.summary.samples
    assert assert_same_samples(run.url, reference.job.out) == reference.summary.samples
    # committed before the kill: kept, not recomputed; the half-written attempts were not adopted
    for task_id, record in run.commits_before.items():
        assert summary.commits[task_id] == record.attempt_id
    for task_id, names in run.half.items():
        assert all(not name.startswith(summary.commits[task_id]) for name in names), (task_id, names)
    for task_id, task in run.before.items():  # the task killed mid-write ran again under a new attempt
        if task.state == RUNNING:
            assert after[task_id].attempts == 2
        elif task.state == PENDING:
            assert after[task_id].attempts == 1


def test_half_shards_are_invisible_then_swept(killed_and_resumed: KilledAndResumed, aws_env: S3Server) -> None:
    """The killed attempt's files were never read (`test_killed_run_left_a_half_shard_readers_ignore`),
    and the resumed driver removed exactly them once the job was complete: the bucket holds the
    commits' files and nothing else, and `sweep_orphans` finds nothing left."""
    run = killed_and_resumed
    assert run.half, "no half-written attempt in the bucket after the kill"
    location = open_location(run.url)
    commits = committed_tasks(location)
    referenced = sorted(path for r in commits for path in (r.shard, r.index_fragment))
    listed = sorted(f"shards/{task}/{name}" for task, names in shard_dirs(run.url).items() for name in names)
    half = {f"shards/{task}/{name}" for task, names in run.half.items() for name in names}
    assert listed == referenced
    assert not half & set(listed)
    assert "leftover files of interrupted attempts" in run.outputs[-1]
    dataset = open_dataset(run.url)
    assert sorted(set(dataset.index.column("shard").to_pylist())) == sorted(r.shard for r in commits)
    samples = len(dataset)
    assert sweep_orphans(location) == []
    remaining = {"/".join(key.split("/")[1:4]) for key in aws_env.keys("resumed/shards/")}
    assert sorted(remaining) == referenced
    assert validate(run.url) == []
    assert len(open_dataset(run.url)) == samples


# ---------------------------------------------------------------------------------------------------------
# (c, d) refused credentials, an unreachable or a silent endpoint: one error line, a failed job, no hang
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FailedRun:
    home: Path
    url: str
    code: int
    output: str
    seconds: float


def failing_submit(inputs: Path, folder: Path, name: str, env: dict[str, str]) -> FailedRun:
    """`datagen submit --out s3://datasets/NAME` with ``env`` over this process's environment and small
    storage timeouts; a run over `FAILURE_BOUND` seconds fails the test (DatagenProcess.wait)."""
    home, url = folder / "home", f"s3://{BUCKET}/{name}"
    with pytest.MonkeyPatch.context() as patch:
        for variable, value in {"DATAGEN_STORAGE_TIMEOUT": "2", "DATAGEN_STORAGE_RETRIES": "1", **env}.items():
            patch.setenv(variable, value)
        with datagen_processes() as start:
            started = time.monotonic()
            process = start([*submit_args(inputs, url, home), "--workers", "1"], folder / "submit.log")
            code = process.wait(timeout=FAILURE_BOUND)
            seconds = time.monotonic() - started
            output = process.output()
    print(f"{name}: exit {code} after {seconds:.1f} s")
    return FailedRun(home, url, code, output, seconds)


@pytest.fixture(scope="module")
def wrong_secret(aws_env: S3Server, inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> FailedRun:
    stop_local_ray()
    return failing_submit(
        inputs, tmp_path_factory.mktemp("wrong"), "wrong-secret", {"AWS_SECRET_ACCESS_KEY": WRONG_SECRET}
    )


@pytest.fixture(scope="module")
def unreachable(aws_env: S3Server, inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> FailedRun:
    stop_local_ray()
    endpoint = f"http://127.0.0.1:{unused_port()}"
    return failing_submit(inputs, tmp_path_factory.mktemp("unreachable"), "unreachable", {"AWS_ENDPOINT_URL": endpoint})


@pytest.fixture(scope="module")
def silent(aws_env: S3Server, inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[FailedRun]:
    """An endpoint that accepts connections and never answers (a stuck or firewalled store): only the
    storage timeout and retry count end the wait."""
    stop_local_ray()
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(128)  # the kernel completes the handshakes; nothing ever reads or replies
        endpoint = f"http://127.0.0.1:{server.getsockname()[1]}"
        env = {"AWS_ENDPOINT_URL": endpoint, "DATAGEN_STORAGE_TIMEOUT": "1"}  # s3fs retries each timeout 5 times
        yield failing_submit(inputs, tmp_path_factory.mktemp("silent"), "silent", env)


def check_failed_run(run: FailedRun, cause: tuple[str, ...]) -> None:
    assert run.code != 0, run.output
    errors = [line for line in run.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, run.output
    (line,) = errors
    assert run.url in line, line
    assert "AWS_ENDPOINT_URL" in line and "AWS_SECRET_ACCESS_KEY" in line, line  # what to check
    assert any(word in line for word in cause), line
    assert "Traceback" not in run.output
    # the store is checked before anything is enqueued: a refused job is never recorded, so no failed
    # job stands in `status` against the dataset it could not reach (issue 52, finding 1)
    assert only_job(run.home) is None
    status = run_datagen(["status", "--home", str(run.home)])
    assert status.returncode == 0, status.stdout + status.stderr
    assert run.url not in status.stdout, status.stdout


def test_wrong_credentials_fail_the_job_with_one_error_line(wrong_secret: FailedRun) -> None:
    check_failed_run(wrong_secret, ("Forbidden", "SignatureDoesNotMatch", "AccessDenied", "InvalidAccessKeyId"))


def test_unreachable_endpoint_fails_the_job_with_one_error_line(unreachable: FailedRun) -> None:
    check_failed_run(unreachable, ("Could not connect", "EndpointConnectionError", "ConnectTimeout"))


def test_silent_endpoint_fails_the_job_after_the_storage_timeout(silent: FailedRun) -> None:
    check_failed_run(silent, ("Read timeout", "ReadTimeoutError", "ConnectTimeout"))


# ---------------------------------------------------------------------------------------------------------
# (e) nothing secret is written
# ---------------------------------------------------------------------------------------------------------


def test_no_secret_in_ledger_dataset_or_output(
    aws_env: S3Server,
    reference: Reference,
    killed_and_resumed: KilledAndResumed,
    wrong_secret: FailedRun,
    unreachable: FailedRun,
    silent: FailedRun,
) -> None:
    secrets = [aws_env.secret.encode(), WRONG_SECRET.encode()]
    ledgers = sorted(
        path
        for home in (reference.home, killed_and_resumed.home, wrong_secret.home, unreachable.home, silent.home)
        for path in home.rglob("*")
        if path.is_file()
    )
    assert sum(path.name == "ledger.db" for path in ledgers) >= 2  # the refused runs record no job
    outputs = [*killed_and_resumed.outputs, wrong_secret.output, unreachable.output, silent.output]
    documents: dict[str, bytes] = {str(path): path.read_bytes() for path in ledgers}
    documents.update({f"output {number}": text.encode() for number, text in enumerate(outputs)})
    client = aws_env.client()
    keys = aws_env.keys("")
    assert "reference/dataset.json" in keys and "resumed/dataset.json" in keys
    for key in keys:  # dataset.json, commits, indexes, shards: every object of the bucket
        documents[key] = client.get_object(Bucket=BUCKET, Key=key)["Body"].read()
    leaks = sorted(name for name, data in documents.items() if any(secret in data for secret in secrets))
    assert leaks == []
