"""Helpers shared by the ledger, engine and fault tests: configs and objects files, `datagen` CLI
subprocesses (with cleanup of every process they leave), /proc process inspection (no psutil), the
ledger seen from outside, and dataset checks (planned samples, identical datasets).

Everything here is Linux-only where it reads /proc; the engine tests are skipped elsewhere.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from jobs.ledger import Job, Ledger, Task
from schemas.dataset import DatasetInfo
from schemas.index import VOLATILE_COLUMNS
from schemas.jobs import TaskSpec
from schemas.shard import array_names
from storage import committed_tasks, init_dataset, open_dataset, open_location, validate
from storage.shards import ShardReader

LEDGER_FILE = "ledger.db"

FAST_BUILTINS = ("capsule", "cone")
"""The quickest built-ins (about 0.3 s a task)."""
SIX_BUILTINS = ("capsule", "cone", "torus", "mug", "bowl", "cylinder_and_ball")
"""Enough work (12 tasks at 2 rotations) for a kill to land while tasks run."""
SHARED_MESH_LINES = ("cow.obj up=y", "teapot.obj up=y", "spot.obj up=y")

T = TypeVar("T")


# ---------------------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------------------


def write_config(path: Path, rotations: int, **fields: Any) -> Path:
    """A generation config TOML: defaults except ``rotations``, ``refiner`` and any top-level scalar fields.

    The refiner is ``none`` unless given: engine behaviour does not depend on it, and the default
    (``poco``) costs ~20 s per task on CPU; tests of poco through the engine pass it explicitly.
    """
    fields = {"refiner": "none", **fields}
    lines = [f"rotations = {rotations}"]
    for key, value in fields.items():
        lines.append(f"{key} = {value!r}" if not isinstance(value, str) else f'{key} = "{value}"')
    path.write_text("\n".join(lines) + "\n")
    return path


def write_objects(path: Path, lines: Sequence[str]) -> Path:
    path.write_text("# objects for an engine test\n" + "\n".join(lines) + "\n")
    return path


def builtin_lines(names: Sequence[str]) -> list[str]:
    return [f"builtin:{name}" for name in names]


@dataclass(frozen=True)
class QueuedJob:
    """A job in a fresh ledger whose dataset the first run has begun, with no task run yet."""

    home: Path
    job: Job
    made: DatasetInfo
    """The dataset's ``dataset.json`` as that first run wrote it."""


def queued_job(folder: Path, config_text: str, objects: str = "builtin:capsule\n") -> QueuedJob:
    """Queue ``objects`` at the config ``config_text`` into ``folder/out`` (ledger ``folder/home``) and
    write the dataset's ``dataset.json`` as a driver does before it runs tasks, without Ray: a test
    then runs tasks with `execute_task` or resumes the job as a later release would."""
    from datagen import api
    from datagen.config_io import load_config
    from datagen.engine.driver import dataset_info
    from datagen.settings import RunSettings

    objects_file = folder / "objects.txt"
    objects_file.write_text(objects)
    config = folder / "config.toml"
    config.write_text(config_text)
    home = folder / "home"
    job = api.enqueue(objects_file, config, RunSettings(home=home, out=str(folder / "out")))
    made = init_dataset(open_location(job.out), dataset_info(load_config(config)))
    return QueuedJob(home, job, made)


def submit_args(inputs: Path, out: str, home: Path) -> list[str]:
    """`datagen submit` of the ``objects.txt`` and ``fast.toml`` in ``inputs`` to ``out``, ledger in ``home``."""
    files = ["--objects", str(inputs / "objects.txt"), "--config", str(inputs / "fast.toml")]
    return ["submit", *files, "--out", out, "--home", str(home)]


# ---------------------------------------------------------------------------------------------------------
# the ledger from outside
# ---------------------------------------------------------------------------------------------------------


def ledger_path(home: Path) -> Path:
    return home / LEDGER_FILE


@contextlib.contextmanager
def open_ledger(home: Path) -> Iterator[Ledger]:
    ledger = Ledger(ledger_path(home))
    try:
        yield ledger
    finally:
        ledger.close()


def only_job(home: Path) -> Job | None:
    """The single job of a home's ledger (None while there is no ledger or no job yet)."""
    if not ledger_path(home).exists():
        return None
    with open_ledger(home) as ledger:
        jobs = ledger.jobs()
    assert len(jobs) <= 1, [j.job_id for j in jobs]
    return jobs[0] if jobs else None


def job_tasks(home: Path, job_id: str) -> list[Task]:
    with open_ledger(home) as ledger:
        return ledger.tasks(job_id)


def planned_task_ids(home: Path, job_id: str) -> list[str]:
    """The job's task ids in planned order (its tasks are ledger rows, not part of its spec)."""
    with open_ledger(home) as ledger:
        return ledger.task_ids(job_id)


def planned_tasks(home: Path, job_id: str) -> list[TaskSpec]:
    """The job's task specs in planned order, as a driver reads them from the ledger."""
    return [TaskSpec.model_validate(task.spec) for task in job_tasks(home, job_id)]


def done_count(home: Path) -> int:
    job = only_job(home)
    if job is None:
        return 0
    with open_ledger(home) as ledger:
        return ledger.task_counts(job.job_id).get("done", 0)


def wait_until(predicate: Callable[[], T], timeout: float, interval: float = 0.05, what: str = "") -> T:
    """Poll until ``predicate()`` is truthy; its value, or AssertionError after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what or predicate}")
        time.sleep(interval)


# ---------------------------------------------------------------------------------------------------------
# processes (/proc only)
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ProcInfo:
    pid: int
    ppid: int
    sid: int
    start: int
    """Start time in clock ticks since boot: (pid, start) names a process even after pid reuse."""
    utime: int
    stime: int
    cmdline: str


def proc_info(pid: int) -> ProcInfo | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    fields = stat[stat.rindex(")") + 2 :].split()  # fields from 3 (state) on
    cmdline = raw.replace(b"\0", b" ").decode(errors="replace").strip()
    if fields[0] == "Z":
        cmdline = f"<zombie> {cmdline}"
    return ProcInfo(
        pid=pid,
        ppid=int(fields[1]),
        sid=int(fields[3]),
        start=int(fields[19]),
        utime=int(fields[11]),
        stime=int(fields[12]),
        cmdline=cmdline,
    )


def all_processes() -> list[ProcInfo]:
    result = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            info = proc_info(int(entry))
            if info is not None:
                result.append(info)
    return result


def descendants(pid: int) -> list[ProcInfo]:
    """Every live descendant of a process (children, their children, ...)."""
    processes = all_processes()
    children: dict[int, list[ProcInfo]] = {}
    for info in processes:
        children.setdefault(info.ppid, []).append(info)
    found, stack = [], [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found.append(child)
            stack.append(child.pid)
    return found


def ray_task_workers(root_pid: int) -> list[ProcInfo]:
    """Ray worker processes below ``root_pid`` that are executing the engine's task right now."""
    return [p for p in descendants(root_pid) if p.cmdline.startswith("ray::_remote_execute")]


def kill_exact(infos: Sequence[ProcInfo], sig: int = signal.SIGKILL) -> None:
    """Signal each process only if it is still the same process (pid and start time match)."""
    for info in infos:
        current = proc_info(info.pid)
        if current is None or current.start != info.start or current.cmdline.startswith("<zombie>"):
            continue
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(info.pid, sig)


def cpu_ticks(infos: Sequence[ProcInfo]) -> int:
    return sum(i.utime + i.stime for i in infos)


# ---------------------------------------------------------------------------------------------------------
# the CLI as a subprocess
# ---------------------------------------------------------------------------------------------------------


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["OPENBLAS_NUM_THREADS"] = "1"
    env["COLUMNS"] = "400"  # rich wraps at 80 columns otherwise, splitting FILE:LINE and paths
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("RAY_ADDRESS", None)  # always a private local Ray
    return env


def datagen_command(*args: str) -> list[str]:
    script = Path(sys.executable).parent / "datagen"
    if script.exists():
        return [str(script), *args]
    return [sys.executable, "-m", "datagen.cli.main", *args]


class DatagenProcess:
    """`datagen ...` in its own session, output to a file; `close()` kills whatever it left behind
    (Ray's raylet, GCS, agents and workers), known by pid and start time, never by name."""

    def __init__(self, args: Sequence[str], log: Path) -> None:
        self.args = list(args)
        self.log = log
        self._handle = open(log, "wb")  # noqa: SIM115 - closed in close()
        self.popen = subprocess.Popen(
            datagen_command(*args),
            stdout=self._handle,
            stderr=subprocess.STDOUT,
            env=subprocess_env(),
            start_new_session=True,
        )
        self._seen: dict[tuple[int, int], ProcInfo] = {}

    @property
    def pid(self) -> int:
        return self.popen.pid

    def snapshot(self) -> list[ProcInfo]:
        """Remember every current descendant (so it can be cleaned up after the driver dies)."""
        found = descendants(self.pid)
        for info in found:
            self._seen[(info.pid, info.start)] = info
        return found

    def session_leftovers(self) -> list[ProcInfo]:
        """Live processes of this session or seen as descendants, other than the driver itself."""
        live = []
        for info in all_processes():
            if info.pid == self.pid or info.cmdline.startswith("<zombie>"):
                continue
            if info.sid == self.pid or (info.pid, info.start) in self._seen:
                live.append(info)
        return live

    def sigkill(self) -> None:
        self.snapshot()
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        self.popen.wait(timeout=30)

    def wait(self, timeout: float) -> int:
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.close()
            raise AssertionError(f"{' '.join(self.args)} ran over {timeout} s:\n{self.output()}") from None

    def poll(self) -> int | None:
        self.snapshot()
        return self.popen.poll()

    def output(self) -> str:
        self._handle.flush()
        return self.log.read_text(errors="replace")

    def close(self) -> None:
        if self.popen.poll() is None:
            self.sigkill()
        leftovers = self.session_leftovers()
        kill_exact(leftovers, signal.SIGTERM)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and self.session_leftovers():
            time.sleep(0.1)
        kill_exact(self.session_leftovers(), signal.SIGKILL)
        self._handle.close()


@contextlib.contextmanager
def datagen_processes() -> Iterator[Callable[..., DatagenProcess]]:
    """A factory of `DatagenProcess` whose processes are all cleaned up on exit."""
    started: list[DatagenProcess] = []

    def start(args: Sequence[str], log: Path) -> DatagenProcess:
        process = DatagenProcess(args, log)
        started.append(process)
        return process

    try:
        yield start
    finally:
        for process in started:
            process.close()


def run_datagen(args: Sequence[str], timeout: float = 240) -> subprocess.CompletedProcess[str]:
    """A short `datagen` command run to completion (for cancel, status, submit --detach)."""
    return subprocess.run(
        datagen_command(*args), capture_output=True, text=True, env=subprocess_env(), timeout=timeout, check=False
    )


# ---------------------------------------------------------------------------------------------------------
# in-process Ray
# ---------------------------------------------------------------------------------------------------------


def wait_for_done_tasks(process: DatagenProcess, home: Path, count: int, before: str) -> None:
    """Wait until the ledger under ``home`` shows ``count`` tasks done while ``process`` still runs
    (``before``: what the test does next, for the message if the process ends first)."""

    def done_while_running() -> bool:
        assert process.poll() is None, f"the driver ended before the {before}:\n{process.output()}"
        return done_count(home) >= count

    wait_until(done_while_running, timeout=180, interval=0.05, what=f"{count} tasks done")


def start_local_ray(num_cpus: int) -> None:
    """A private local Ray with ``num_cpus`` worker CPUs, started the way the engine starts it."""
    import ray

    from datagen.engine.driver import ensure_ray

    if ray.is_initialized():
        ray.shutdown()
    os.environ.pop("RAY_ADDRESS", None)
    ensure_ray(None, num_cpus)


def stop_local_ray() -> None:
    import ray

    if ray.is_initialized():
        ray.shutdown()


# ---------------------------------------------------------------------------------------------------------
# datasets
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DatasetSummary:
    commits: dict[str, str]
    """task id -> committed attempt id."""
    samples: int
    planned: int
    """Sum over committed tasks of cases minus dropped_empty (shard metadata)."""
    cases: int
    sample_ids: list[str]
    seconds: dict[str, float]
    """task id -> the task's compute seconds (sum of its timed steps)."""


def summarize(url: str) -> DatasetSummary:
    location = open_location(url)
    commits = committed_tasks(location)
    planned = cases = 0
    seconds = {}
    for record in commits:
        attributes = ShardReader(location, record.shard).attributes
        assert attributes.num_samples == record.num_samples
        meta = attributes.metadata
        cases += int(meta["cases"])
        planned += int(meta["cases"]) - int(meta["dropped_empty"])
        assert int(meta["cases"]) - int(meta["dropped_empty"]) == record.num_samples, record.task_id
        seconds[record.task_id] = float(sum(meta["seconds"].values()))
    dataset = open_dataset(url)
    return DatasetSummary(
        commits={r.task_id: r.attempt_id for r in commits},
        samples=len(dataset),
        planned=planned,
        cases=cases,
        sample_ids=dataset.index.column("sample_id").to_pylist(),
        seconds=seconds,
    )


def check_complete_dataset(url: str, task_ids: Sequence[str]) -> DatasetSummary:
    """A sound dataset holding exactly the planned samples of exactly these tasks, none twice."""
    problems = validate(url, full=True)
    assert problems == [], problems
    summary = summarize(url)
    assert sorted(summary.commits) == sorted(task_ids)
    assert summary.samples == summary.planned > 0
    assert len(set(summary.sample_ids)) == len(summary.sample_ids), "duplicate sample ids"
    return summary


def shard_dirs(url: str) -> dict[str, list[str]]:
    """task id -> the attempt files under shards/<task>/ (one .zarr and one .parquet per execution)."""
    location = open_location(url)
    return {task: location.listdir(f"shards/{task}") for task in location.listdir("shards")}


def assert_same_samples(url_a: str, url_b: str) -> int:
    """Identical samples, matched by sample id: points/observed keys and masks of every sample, every
    array of every committed shard, and every index column except the volatile ones. Returns the
    number of samples compared."""
    a, b = open_dataset(url_a), open_dataset(url_b)
    ids_a = a.index.column("sample_id").to_pylist()
    ids_b = b.index.column("sample_id").to_pylist()
    assert sorted(ids_a) == sorted(ids_b)
    assert len(set(ids_a)) == len(ids_a)
    where_b = {sample: i for i, sample in enumerate(ids_b)}
    for i, sample in enumerate(ids_a):
        j = where_b[sample]
        for source in ("points", "observed"):
            np.testing.assert_array_equal(a.keys(i, source), b.keys(j, source), err_msg=f"{sample} {source}")
        assert a.masks(i) == b.masks(j), sample
    columns = [name for name in a.index.column_names if name not in VOLATILE_COLUMNS]
    table_a = a.index.select(columns).sort_by("sample_id")
    table_b = b.index.select(columns).sort_by("sample_id")
    for name in columns:
        assert table_a.column(name).equals(table_b.column(name)), f"index column {name} differs"
    location_a, location_b = open_location(url_a), open_location(url_b)
    commits_b = {r.task_id: r for r in committed_tasks(location_b)}
    assert a.info.schema_version == b.info.schema_version
    for record in committed_tasks(location_a):
        shard_a = ShardReader(location_a, record.shard)
        shard_b = ShardReader(location_b, commits_b[record.task_id].shard)
        for name in array_names(a.info.schema_version):
            np.testing.assert_array_equal(shard_a.array(name), shard_b.array(name), err_msg=f"{record.task_id} {name}")
    return len(ids_a)
