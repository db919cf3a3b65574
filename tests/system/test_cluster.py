"""Several Ray nodes on one machine (`ray.cluster_utils.Cluster`): a head that schedules no work and
two 1-CPU worker nodes, each with its own raylet. A job's tasks must run on both workers (the ledger
records where), and a worker node removed mid-job must cost nothing: Ray re-runs its tasks on the
node left, and the dataset ends with exactly the planned samples, each once, identical to the
uninterrupted run.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest
from support.engine import (
    SIX_BUILTINS,
    assert_same_samples,
    builtin_lines,
    check_complete_dataset,
    done_count,
    job_tasks,
    planned_task_ids,
    ray_task_workers,
    stop_local_ray,
    wait_until,
    write_config,
    write_objects,
)

from datagen import api
from datagen.settings import RunSettings
from jobs.ledger import DONE, Job

pytestmark = [
    pytest.mark.skipif(not sys.platform.startswith("linux"), reason="engine tests read /proc (Linux)"),
    pytest.mark.slow,
    pytest.mark.ray,
]

OBJECT_STORE_BYTES = 100 * 1024**2
TASKS = len(SIX_BUILTINS) * 2


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    """Head (0 CPUs: it only schedules) + 2 worker nodes of 1 CPU each; the driver is this process."""
    import ray
    from ray.cluster_utils import Cluster

    stop_local_ray()  # another module's private Ray must not be what the engine connects to
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "object_store_memory": OBJECT_STORE_BYTES, "include_dashboard": False},
    )
    try:
        for _ in range(2):
            cluster.add_node(num_cpus=1, object_store_memory=OBJECT_STORE_BYTES)
        cluster.wait_for_nodes()
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("inputs")
    write_config(folder / "fast.toml", rotations=2)
    write_objects(folder / "six.txt", builtin_lines(SIX_BUILTINS))
    return folder


def settings_for(home: Path, cluster: Any) -> RunSettings:
    return RunSettings(home=home, ray_address=cluster.address)


def node_ids(nodes: Iterable[Any]) -> list[str]:
    """The placement prefixes (node id [:12]) of cluster_utils nodes, sorted."""
    return sorted(node.node_id[:12] for node in nodes)


@pytest.fixture(scope="module")
def reference(cluster: Any, inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Job, list[str]]:
    """6 built-ins x 2 rotations on the 2 worker nodes, uninterrupted; also the worker node ids."""
    import ray

    workers = node_ids(cluster.worker_nodes)
    home = tmp_path_factory.mktemp("reference")
    job = api.submit(inputs / "six.txt", inputs / "fast.toml", settings_for(home, cluster))
    assert ray.cluster_resources()["CPU"] == 2
    return home, job, workers


def test_tasks_run_on_both_worker_nodes(reference: tuple[Path, Job, list[str]], cluster: Any) -> None:
    import ray

    home, job, workers = reference
    assert job.state == DONE, job.summary
    task_ids = planned_task_ids(home, job.job_id)
    assert len(task_ids) == TASKS
    summary = check_complete_dataset(job.out, task_ids)
    assert job.summary is not None and job.summary["samples"] == summary.samples
    tasks = job_tasks(home, job.job_id)
    assert sorted(t.task_id for t in tasks) == sorted(task_ids)
    assert all(t.state == DONE and t.placement for t in tasks), [(t.task_id, t.state, t.placement) for t in tasks]
    placed_on = sorted({str(t.placement).split("@", 1)[0] for t in tasks})
    assert placed_on == workers, f"placements {placed_on}, worker nodes {workers}"
    # the driver is attached to the head, which ran no task (num_cpus=0)
    assert ray.get_runtime_context().get_node_id() == cluster.head_node.node_id
    assert cluster.head_node.node_id[:12] not in placed_on


def test_worker_node_removed_mid_job(
    reference: tuple[Path, Job, list[str]], cluster: Any, inputs: Path, tmp_path: Path
) -> None:
    """A worker node's raylet and workers are killed while tasks run on it; the job still ends with
    the reference's samples, none twice."""
    from ray._private.ray_constants import PROCESS_TYPE_RAYLET

    _, ref_job, workers = reference
    home = tmp_path / "home"
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["job"] = api.submit(inputs / "six.txt", inputs / "fast.toml", settings_for(home, cluster))
        except BaseException as exc:  # reported by the main thread
            outcome["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    victim = min(cluster.worker_nodes, key=lambda node: node.node_id)
    victim_id = victim.node_id[:12]
    raylet_pid = victim.all_processes[PROCESS_TYPE_RAYLET][0].process.pid

    def busy_on_victim() -> bool:
        """Some tasks done, and one executing right now in a worker process of the victim's raylet."""
        assert thread.is_alive(), f"the job ended before the node was removed: {outcome}"
        return done_count(home) >= 2 and bool(ray_task_workers(raylet_pid))

    wait_until(busy_on_victim, timeout=240, interval=0.05, what="2 tasks done and one running on the victim")
    done_at_removal = done_count(home)
    cluster.remove_node(victim, allow_graceful=False)
    thread.join(timeout=300)
    assert not thread.is_alive(), "the job did not finish after the node was removed"
    assert "error" not in outcome, outcome.get("error")
    job: Job = outcome["job"]
    assert done_at_removal < TASKS, "the node was removed after the job's end"
    assert job.state == DONE, job.summary
    summary = check_complete_dataset(job.out, planned_task_ids(home, job.job_id))
    assert assert_same_samples(job.out, ref_job.out) == summary.samples
    tasks = job_tasks(home, job.job_id)
    # Ray re-ran the lost task inside the ledger's attempt: nothing failed, nothing claimed twice
    assert all(t.state == DONE and t.attempts == 1 for t in tasks), [(t.task_id, t.state, t.error) for t in tasks]
    placed_on = sorted({str(t.placement).split("@", 1)[0] for t in tasks})
    print(f"removed {victim_id} with {done_at_removal}/{TASKS} done; placements {placed_on}")
    assert placed_on == workers  # both ran tasks; the survivor finished the job
    (survivor_node,) = cluster.worker_nodes
    survivor = survivor_node.node_id[:12]
    assert survivor != victim_id and survivor in placed_on
