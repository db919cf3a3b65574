"""Crash safety of the commit protocol with real processes killed by SIGKILL.

A "zygote" subprocess imports storage, loads a pickled `ShardPayload` and warms zarr up once; for
each run it forks a writer child that calls `write_task`, either killing itself right after a chosen
step of the protocol (the step functions are wrapped inside the child only) or being killed by the
test after a seeded random delay. After every kill the dataset must show the task either not at all
or whole, and a re-run must leave exactly one copy.
"""

from __future__ import annotations

import json
import os
import pickle
import select
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import storage as fx

from schemas.shard import array_names
from storage.checks import validate
from storage.dataset import (
    ShardPayload,
    commit_path,
    committed_tasks,
    fragment_path,
    init_dataset,
    read_commit,
    shard_path,
    sweep_orphans,
    write_task,
)
from storage.readers import open_dataset
from storage.shards import ShardReader
from storage.store import Location, open_location

RANDOM_KILLS = 43
"""Children actually killed mid-write at random times (a child that finished first does not count)."""
RANDOM_SEED = 20260311

ZYGOTE = textwrap.dedent(
    r'''
    import json, os, pickle, signal, sys, tempfile, time, traceback

    import zarr
    import storage.store.location as location_module
    import storage.dataset.writer as writer_module
    from storage.dataset import init_dataset
    from storage.store import Location, open_location

    with open(sys.argv[1], "rb") as handle:
        payload, info = pickle.load(handle)


    def die():
        os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(60)  # never reached


    class OsProxy:
        """storage.store.location's view of os, so that only its own replace/link calls are intercepted."""

        def __init__(self, before_replace=None, before_link=None):
            self.before_replace, self.before_link = before_replace, before_link

        def __getattr__(self, name):
            return getattr(os, name)

        def replace(self, *args):
            if self.before_replace:
                self.before_replace()
            return os.replace(*args)

        def link(self, *args):
            if self.before_link:
                self.before_link()
            return os.link(*args)


    def pause(flag):
        open(flag + ".reached", "w").close()
        deadline = time.time() + 60
        while not os.path.exists(flag) and time.time() < deadline:
            time.sleep(0.005)


    def install(point, flag):
        """Make this (child) process stop at `point` of the commit protocol."""
        if point == "start":
            die()
        if point == "mid_shard":  # some arrays of the group written, not all
            original_create = zarr.Group.create_array
            calls = [0]

            def create_array(self, *args, **kwargs):
                calls[0] += 1
                if calls[0] == 5:
                    die()
                return original_create(self, *args, **kwargs)

            zarr.Group.create_array = create_array
        if point == "shard":
            original_group = writer_module.write_shard_group

            def write_shard_group(*args, **kwargs):
                original_group(*args, **kwargs)
                die()

            writer_module.write_shard_group = write_shard_group
        if point == "shard_tmp":  # the shard file's bytes in a temporary file, not yet renamed
            location_module.os = OsProxy(before_replace=die)
        if point == "fragment_tmp":  # fragment bytes in a temporary file, not yet renamed
            replaced = [0]

            def second_replace():
                replaced[0] += 1
                if replaced[0] == 2:  # the shard file's rename was the first
                    die()

            location_module.os = OsProxy(before_replace=second_replace)
        if point == "commit_tmp":  # commit record in a temporary file, not yet linked into place
            location_module.os = OsProxy(before_link=die)
        if point in ("fragment", "pause_fragment"):
            original_atomic = Location.write_atomic

            def write_atomic(self, relative, data):
                original_atomic(self, relative, data)
                if relative.endswith(".parquet"):
                    if point == "fragment":
                        die()
                    pause(flag)

            Location.write_atomic = write_atomic
        if point == "commit":
            original_exclusive = Location.create_exclusive

            def create_exclusive(self, relative, data):
                created = original_exclusive(self, relative, data)
                die()
                return created

            Location.create_exclusive = create_exclusive


    def child(command):
        try:
            install(command["point"], command.get("flag"))
            record = writer_module.write_task(open_location(command["root"]), payload, command["attempt"])
            if command.get("result"):
                with open(command["result"], "w") as handle:
                    handle.write(record.model_dump_json())
        except BaseException:
            traceback.print_exc()
            sys.stderr.flush()
            os._exit(1)
        os._exit(0)


    # Warm up in this process (imports, zarr's IO loop, pyarrow) so that each forked child writes at
    # full speed; zarr and pyarrow reset their threads in a forked child.
    with tempfile.TemporaryDirectory() as scratch:
        warm = open_location(scratch)
        init_dataset(warm, info)
        writer_module.write_task(warm, payload, "warm-up")

    def reply(message):
        sys.stdout.write(json.dumps(message) + "\n")
        sys.stdout.flush()

    reply({"ready": True})
    child_pid = None
    for line in sys.stdin:
        command = json.loads(line)
        if command["op"] == "write":
            sys.stdout.flush()
            sys.stderr.flush()
            child_pid = os.fork()
            if child_pid == 0:
                child(command)
            reply({"pid": child_pid})
        elif command["op"] == "reap":
            _, status = os.waitpid(child_pid, 0)
            reply({
                "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
                "exit": os.WEXITSTATUS(status) if os.WIFEXITED(status) else None,
            })
        elif command["op"] == "exit":
            break
    '''
)


class Zygote:
    """The forking writer process and its line protocol (one JSON line per request and reply)."""

    def __init__(self, folder: Path, payload: ShardPayload) -> None:
        script = folder / "zygote.py"
        script.write_text(ZYGOTE)
        data = folder / "payload.pkl"
        data.write_bytes(pickle.dumps((payload, fx.dataset_info())))
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
        self.proc = subprocess.Popen(
            [sys.executable, str(script), str(data)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._buffer = b""
        assert self._read(timeout=120) == {"ready": True}

    def _read(self, timeout: float = 30.0) -> dict[str, Any]:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("the writer zygote did not answer")
            ready, _, _ = select.select([fd], [], [], remaining)
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    raise RuntimeError(f"the writer zygote exited (rc {self.proc.poll()})")
                self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        return dict(json.loads(line))

    def _send(self, message: dict[str, Any]) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write((json.dumps(message) + "\n").encode())
        self.proc.stdin.flush()

    def start(self, root: Path, attempt: str, point: str = "none", **extra: str) -> int:
        self._send({"op": "write", "root": str(root), "attempt": attempt, "point": point, **extra})
        return int(self._read()["pid"])

    def reap(self) -> dict[str, Any]:
        self._send({"op": "reap"})
        return self._read(timeout=60)

    def run(self, root: Path, attempt: str, point: str = "none", kill_after: float | None = None) -> dict[str, Any]:
        """One writer child; ``kill_after`` seconds: SIGKILL it from here (a no-op once it has exited:
        the zygote reaps only afterwards, so the pid cannot have been reused)."""
        started = time.monotonic()
        pid = self.start(root, attempt, point)
        if kill_after is not None:
            time.sleep(max(0.0, kill_after - (time.monotonic() - started)))
            os.kill(pid, signal.SIGKILL)
        status = self.reap()
        status["seconds"] = time.monotonic() - started
        return status

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self._send({"op": "exit"})
                self.proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def payload() -> ShardPayload:
    return fx.small_payload()


@pytest.fixture(scope="module")
def zygote(tmp_path_factory: pytest.TempPathFactory, payload: ShardPayload) -> Any:
    process = Zygote(tmp_path_factory.mktemp("zygote"), payload)
    yield process
    process.close()


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty dataset (dataset.json only) copied for every run."""
    root = tmp_path_factory.mktemp("template") / "ds"
    init_dataset(open_location(str(root)), fx.dataset_info())
    return root


def fresh(template: Path, folder: Path, name: str) -> Path:
    root = folder / name
    shutil.copytree(template, root)
    return root


def assert_whole(root: Path, payload: ShardPayload, attempt: str) -> None:
    """The task is committed to ``attempt`` and every byte of it reads back as written."""
    task_id = payload.attributes.task_id
    location = open_location(str(root))
    record = read_commit(location, task_id)
    assert record is not None and record.attempt_id == attempt
    ds = open_dataset(str(root))
    count = payload.attributes.num_samples
    assert len(ds) == count
    assert ds.index.column("sample_id").to_pylist() == payload.index_rows["sample_id"]
    assert set(ds.index.column("attempt_id").to_pylist()) == {attempt}
    assert set(ds.index.column("shard").to_pylist()) == {shard_path(task_id, attempt)}
    offsets = payload.arrays["points_offsets"]
    for i in range(count):
        row = int(ds.index.column("row")[i].as_py())
        np.testing.assert_array_equal(
            ds.keys(i, "points"), payload.arrays["points_keys"][offsets[row] : offsets[row + 1]]
        )
        assert ds.masks(i) == tuple(int(v) for v in payload.arrays["masks"][row])
    reader = ShardReader(location, record.shard)
    for name in array_names():
        np.testing.assert_array_equal(reader.array(name), payload.arrays[name])
        assert reader.array(name).dtype == payload.arrays[name].dtype
    assert validate(str(root), full=True) == []


def assert_absent(root: Path) -> None:
    assert committed_tasks(open_location(str(root))) == []
    assert len(open_dataset(str(root))) == 0
    assert validate(str(root), full=True) == []


def rerun_and_sweep(root: Path, payload: ShardPayload, killed: str, was_committed: bool) -> None:
    """A re-run with a new attempt id leaves exactly one copy; a sweep then leaves only it."""
    location = open_location(str(root))
    task_id = payload.attributes.task_id
    record = write_task(location, payload, "rerun")
    expected = killed if was_committed else "rerun"
    assert record.attempt_id == expected
    ids = open_dataset(str(root)).index.column("sample_id").to_pylist()
    assert len(ids) == len(set(ids)) == payload.attributes.num_samples
    removed = sweep_orphans(location)
    assert all(path.startswith(f"shards/{task_id}/") for path in removed)
    assert shard_path(task_id, expected) not in removed and fragment_path(task_id, expected) not in removed
    left = set(location.listdir(f"shards/{task_id}"))
    assert left == {f"{expected}.zarr.zip", f"{expected}.parquet"}
    assert_whole(root, payload, expected)


STEPS = {
    # point: whether the task is committed after a kill there
    "start": False,
    "mid_shard": False,
    "shard_tmp": False,
    "shard": False,
    "fragment_tmp": False,
    "fragment": False,
    "commit_tmp": False,
    "commit": True,
}


def test_kill_at_each_protocol_step(zygote: Zygote, template: Path, payload: ShardPayload, tmp_path: Path) -> None:
    for point, committed in STEPS.items():
        root = fresh(template, tmp_path, point)
        status = zygote.run(root, f"killed-{point}", point)
        assert status["signal"] == signal.SIGKILL, (point, status)
        files = {str(p.relative_to(root)) for p in root.rglob("*")}
        if point not in ("start", "mid_shard"):  # a shard's members are put together in memory
            assert any(p.startswith("shards/") for p in files), point  # something was written
        if committed:
            assert_whole(root, payload, f"killed-{point}")
        else:
            assert_absent(root)
        rerun_and_sweep(root, payload, f"killed-{point}", committed)


def test_kill_at_random_times(zygote: Zygote, template: Path, payload: ShardPayload, tmp_path: Path) -> None:
    control = [zygote.run(fresh(template, tmp_path, f"control-{i}"), "control") for i in range(3)]
    assert all(s["exit"] == 0 for s in control), control
    duration = float(np.median([s["seconds"] for s in control]))
    delays = np.random.default_rng(RANDOM_SEED).uniform(0.0, 1.15 * duration, 3 * RANDOM_KILLS)
    outcomes = {"killed, absent": 0, "killed, committed": 0, "finished": 0}
    for k, delay in enumerate(delays):
        if outcomes["killed, absent"] + outcomes["killed, committed"] >= RANDOM_KILLS:
            break
        root = fresh(template, tmp_path, f"random-{k}")
        attempt = f"random-{k}"
        status = zygote.run(root, attempt, kill_after=float(delay))
        assert status["signal"] == signal.SIGKILL or status["exit"] == 0, status
        committed = read_commit(open_location(str(root)), payload.attributes.task_id) is not None
        if committed:
            assert_whole(root, payload, attempt)
        else:
            assert status["signal"] == signal.SIGKILL, status
            assert_absent(root)
        key = "finished" if status["exit"] == 0 else ("killed, committed" if committed else "killed, absent")
        outcomes[key] += 1
        rerun_and_sweep(root, payload, attempt, committed)
    print(f"control write {duration * 1000:.0f} ms; random kills: {outcomes}")
    # With the 7 kills of test_kill_at_each_protocol_step: at least 50 real SIGKILLs.
    assert outcomes["killed, absent"] + outcomes["killed, committed"] >= RANDOM_KILLS, outcomes


def test_late_attempt_never_replaces_the_commit(
    zygote: Zygote, template: Path, payload: ShardPayload, tmp_path: Path
) -> None:
    """Attempt B has written its shard and fragment when A commits; B's commit then loses."""
    root = fresh(template, tmp_path, "late")
    task_id = payload.attributes.task_id
    flag = tmp_path / "release-b"
    result = tmp_path / "b-result.json"
    pid = zygote.start(root, "B", "pause_fragment", flag=str(flag), result=str(result))
    location = open_location(str(root))
    try:
        deadline = time.monotonic() + 60
        while not Path(f"{flag}.reached").exists():
            assert time.monotonic() < deadline, "attempt B never reached its pause"
            time.sleep(0.01)
        assert read_commit(location, task_id) is None
        assert location.exists(shard_path(task_id, "B")) and location.exists(fragment_path(task_id, "B"))
        assert write_task(location, payload, "A").attempt_id == "A"
    finally:
        flag.touch()  # release B whatever happened
    status = zygote.reap()
    assert status["exit"] == 0, (pid, status)
    assert json.loads(result.read_text())["attempt_id"] == "A"  # B was told who won
    assert_whole(root, payload, "A")
    # A later attempt C after the commit writes nothing and returns A's record.
    assert write_task(location, payload, "C").attempt_id == "A"
    assert not location.exists(shard_path(task_id, "C")) and not location.exists(fragment_path(task_id, "C"))
    assert_whole(root, payload, "A")
    assert sweep_orphans(location) == sorted([shard_path(task_id, "B"), fragment_path(task_id, "B")])
    assert_whole(root, payload, "A")


def test_sweep_orphans_removes_only_uncommitted_attempts_of_committed_tasks(tmp_path: Path) -> None:
    first, second = fx.payloads()
    t1, t2 = first.attributes.task_id, second.attributes.task_id
    location: Location = fx.build_dataset(str(tmp_path / "ds"), task_payloads=[])
    # Task 1: attempt "old" wrote everything but lost its commit; "new" committed.
    write_task(location, first, "old")
    location.remove(commit_path(t1))
    write_task(location, first, "new")
    location.write_atomic(f"shards/{t1}/dead.parquet.tmp-0123", b"partial")
    # Task 2: an attempt without a commit (may still be running): must be left alone.
    write_task(location, second, "running")
    location.remove(commit_path(t2))
    before_t2 = set(location.listdir(f"shards/{t2}"))

    removed = sweep_orphans(location)
    assert removed == sorted([shard_path(t1, "old"), fragment_path(t1, "old"), f"shards/{t1}/dead.parquet.tmp-0123"])
    assert set(location.listdir(f"shards/{t1}")) == {"new.zarr.zip", "new.parquet"}
    assert set(location.listdir(f"shards/{t2}")) == before_t2 == {"running.zarr.zip", "running.parquet"}
    assert sweep_orphans(location) == []
    ds = open_dataset(location.url)
    assert len(ds) == first.attributes.num_samples
    assert set(ds.index.column("attempt_id").to_pylist()) == {"new"}
    assert validate(location.url, full=True) == []
