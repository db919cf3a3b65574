"""One refiner per node (datagen/engine/refiner_host.py) through the engine on a real local Ray.

The shared host's samples are those of refiners in the tasks, bit for bit: with two tasks at once
on one host (this module's Ray: 3 CPUs, one for the host) and with one (`datagen submit --workers 2
--shared-refiner`, its own Ray); a host SIGKILLed mid-job is restarted and its calls sent again,
leaving a dataset equal to the clean run's; the step table says what the tasks waited on the host.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest
from support.engine import (
    assert_same_samples,
    builtin_lines,
    datagen_processes,
    only_job,
    start_local_ray,
    stop_local_ray,
    write_config,
    write_objects,
)

from datagen import api
from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS
from datagen.settings import RunSettings
from jobs.ledger import DONE
from storage import open_dataset, open_location, read_commit, validate

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.skipif(not BUILTIN_WEIGHTS.is_file(), reason="no shipped POCO weights"),
    pytest.mark.ray,
    pytest.mark.slow,
]

RAY_CPUS = 3
"""Two tasks at once beside the host's CPU."""


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    start_local_ray(RAY_CPUS)
    yield
    stop_local_ray()


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[Path, Path, str]:
    """(objects, config, dataset) of the capsule's two rotations, each task refining in itself."""
    folder = tmp_path_factory.mktemp("clean")
    config = write_config(folder / "poco.toml", rotations=2, refiner="poco")
    objects = write_objects(folder / "objects.txt", builtin_lines(("capsule",)))
    job = api.submit(objects, config, RunSettings(home=folder / "home", num_workers=RAY_CPUS, ray_address=None))
    assert job.state == DONE, job.summary
    return objects, config, job.out


def host_handles() -> list:
    import ray

    names = sorted(name for name in ray.util.list_named_actors() if name.startswith("datagen-refiner-"))
    return [ray.get_actor(name) for name in names]


def test_a_host_killed_mid_job_leaves_the_clean_runs_dataset(clean, tmp_path: Path) -> None:
    """Two tasks at once on one host, which is SIGKILLed after its first answer: Ray restarts it
    and sends the calls again; every sample equals the clean run's, and each task's steps say
    what it waited on the host."""
    import ray

    objects, config, clean_out = clean
    settings = RunSettings(home=tmp_path / "home", num_workers=RAY_CPUS, ray_address=None, shared_refiner=True)
    finished: dict[str, object] = {}
    runner = threading.Thread(target=lambda: finished.update(job=api.submit(objects, config, settings)))
    runner.start()
    deadline = time.monotonic() + 300
    killed = False
    while runner.is_alive() and time.monotonic() < deadline and not killed:
        for handle in host_handles():
            try:
                if ray.get(handle.served.remote(), timeout=5) >= 1 and runner.is_alive():
                    os.kill(ray.get(handle.pid.remote(), timeout=5), signal.SIGKILL)
                    killed = True
            except (ray.exceptions.RayError, ProcessLookupError):
                continue
        time.sleep(0.2)
    runner.join(timeout=600)
    assert killed, "the host was never seen serving while the job ran"
    job = finished["job"]
    assert job.state == DONE, job.summary
    assert host_handles() == []  # the driver stops its hosts
    assert validate(job.out, full=True) == []
    assert assert_same_samples(clean_out, job.out) > 0
    location = open_location(job.out)
    for task_id in sorted(open_dataset(job.out).index.column("task_id").unique().to_pylist()):
        steps = read_commit(location, task_id).timings.steps
        assert steps["refiner_host"].cpu > 0 and "refiner_queue" in steps
    assert "refiner_host" in job.summary["step_seconds"]["steps"]


def test_one_task_at_a_time_on_a_shared_host_gives_the_same_samples(clean, tmp_path: Path) -> None:
    """`datagen submit --workers 2 --shared-refiner`: one CPU for the host, one for the tasks."""
    objects, config, clean_out = clean
    home, out = tmp_path / "home", tmp_path / "out"
    args = ["submit", "--objects", str(objects), "--config", str(config), "--workers", "2", "--shared-refiner"]
    args += ["--home", str(home), "--out", str(out)]
    with datagen_processes() as start:
        process = start(args, tmp_path / "submit.log")
        assert process.wait(timeout=600) == 0, process.output()
        output = process.output()
    job = only_job(home)
    assert job is not None and job.state == DONE
    assert "refiner_host" in output and "refiner_queue" in output  # the step table names the host's part
    assert assert_same_samples(clean_out, str(out)) > 0
