"""Benchmark: job throughput on a local multi-node Ray cluster with 1, 2 and 3 worker nodes.

    python -m benchmarks.generation.cluster [--objects examples/builtin.txt] [--first N] [--rotations 2]
        [--refiner none] [--nodes 1 2 3]

For each node count it starts a `ray.cluster_utils.Cluster` on this machine: a head with 0 CPUs (it
only schedules, as in docker-compose.yml) and N worker nodes of 1 CPU each, every one its own raylet
and object store (100 MB). The driver (this process) connects with ``RunSettings(ray_address=...)``
and runs, through `datagen.api.submit`, a small warm-up job (2 tasks per node, so every node has
started worker processes that imported the pipeline) and then the timed job: every object of the
objects file (default: the 22 built-ins; ``--first N`` keeps the first N) x ``--rotations``, refiner
``none`` unless ``--refiner`` says otherwise. Printed per node count: tasks, samples, wall seconds
(cluster start-up and warm-up excluded), tasks/s, samples/s, tasks per node (from the placements
the ledger records), a task's mean compute seconds, the cores this process tree used, the other
processes' load in cores and the load average before and after; then the scaling of tasks/s and
samples/s over the 1-node run of the same invocation.

Each worker node runs one task at a time, so N nodes can use N cores at most. On a 2-core machine no
gain is expected past 2 nodes (3 nodes share 2 cores, and the driver, the GCS and 4 raylets compete
with them); a gain past 2 needs as many free cores as nodes. Linux only (reads /proc).
"""

from __future__ import annotations

import os

from benchmarks.common import REPO_ROOT, limit_threads

limit_threads()
os.environ.pop("RAY_ADDRESS", None)

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

from datagen import api  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.settings import RunSettings  # noqa: E402
from jobs.ledger import DONE, Ledger  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402
from storage import ShardReader, committed_tasks, open_location  # noqa: E402

OBJECT_STORE_BYTES = 100 * 1024**2
TICKS = os.sysconf("SC_CLK_TCK")
WARM_UP_OBJECTS = ("builtin:capsule", "builtin:cone")


def machine_busy_ticks() -> int:
    """Busy jiffies of all CPUs since boot: user + nice + system + irq + softirq + steal."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return user + nice + system + irq + softirq + steal


def loadavg() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def task_seconds(url: str) -> list[float]:
    """Each committed task's own compute seconds (its timed steps, from the shard metadata)."""
    location = open_location(url)
    seconds = []
    for record in committed_tasks(location):
        meta = ShardReader(location, record.shard).attributes.metadata
        seconds.append(float(sum(meta["seconds"].values())))
    return seconds


def own_tree_ticks() -> dict[int, int]:
    """pid -> utime + stime of this process and its descendants (the cluster's raylets, GCS, workers)."""
    table: dict[int, tuple[int, int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        table[int(entry)] = (int(fields[1]), int(fields[11]) + int(fields[12]))
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    tree, stack = {}, [os.getpid()]
    while stack:
        pid = stack.pop()
        if pid in table:
            tree[pid] = table[pid][1]
        stack.extend(children.get(pid, []))
    return tree


@dataclass(frozen=True)
class Result:
    nodes: int
    tasks: int
    samples: int
    wall: float
    per_node: list[int]
    """Tasks run by each worker node, most first."""
    task_seconds: float
    """Mean compute seconds of a task (single-threaded steps): grows when the nodes share cores."""
    own_cores: float
    """CPU time of this process tree (driver, GCS, raylets, workers) over the wall time."""
    background_cores: float
    """Busy CPU of the machine's other processes over the wall time."""
    load_before: str
    load_after: str

    @property
    def tasks_per_second(self) -> float:
        return self.tasks / self.wall

    @property
    def samples_per_second(self) -> float:
        return self.samples / self.wall


def objects_file(source: Path, first: int | None, folder: Path) -> Path:
    """The objects file to time: ``source``, or its first ``first`` object lines."""
    if first is None:
        return source
    lines = [line for line in source.read_text().splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if first > len(lines):
        raise SystemExit(f"--first {first}: {source} has {len(lines)} objects")
    subset = folder / "objects.txt"
    subset.write_text("\n".join(lines[:first]) + "\n")
    return subset


def tasks_per_node(home: Path, job_id: str) -> list[int]:
    ledger = Ledger(home / "ledger.db")
    try:
        counts = Counter(str(t.placement).split("@", 1)[0] for t in ledger.tasks(job_id) if t.state == DONE)
    finally:
        ledger.close()
    return sorted(counts.values(), reverse=True)


def run(nodes: int, objects: Path, config: GenerationConfig, folder: Path) -> Result:
    import ray
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "object_store_memory": OBJECT_STORE_BYTES, "include_dashboard": False},
    )
    try:
        for _ in range(nodes):
            cluster.add_node(num_cpus=1, object_store_memory=OBJECT_STORE_BYTES)
        cluster.wait_for_nodes()
        warm = folder / f"warm-{nodes}"
        warm.mkdir(parents=True)
        (warm / "objects.txt").write_text("\n".join(WARM_UP_OBJECTS) + "\n")
        warm_config = config.model_copy(update={"rotations": max(1, nodes)})
        api.submit(warm / "objects.txt", warm_config, RunSettings(home=warm, ray_address=cluster.address))

        home = folder / f"run-{nodes}"
        load_before, busy_before, tree_before = loadavg(), machine_busy_ticks(), own_tree_ticks()
        started = time.perf_counter()
        job = api.submit(objects, config, RunSettings(home=home, ray_address=cluster.address))
        wall = time.perf_counter() - started
        load_after, busy_after, tree_after = loadavg(), machine_busy_ticks(), own_tree_ticks()
    finally:
        ray.shutdown()
        cluster.shutdown()
    if job.state != DONE:
        raise SystemExit(f"job {job.job_id} on {nodes} nodes ended {job.state}: {job.summary}")
    summary = job.summary or {}
    own = sum(ticks - tree_before.get(pid, 0) for pid, ticks in tree_after.items()) / TICKS
    seconds = task_seconds(job.out)
    return Result(
        nodes=nodes,
        tasks=int(summary.get("done", 0)),
        samples=int(summary.get("samples", 0)),
        wall=wall,
        per_node=tasks_per_node(home, job.job_id),
        task_seconds=statistics.fmean(seconds) if seconds else float("nan"),
        own_cores=own / wall,
        background_cores=max(0.0, (busy_after - busy_before) / TICKS - own) / wall,
        load_before=load_before,
        load_after=load_after,
    )


def report(result: Result) -> None:
    per_node = "/".join(str(n) for n in result.per_node)
    print(
        f"{result.nodes:>5}  {result.tasks:>5}  {result.samples:>7}  {result.wall:>7.1f}  "
        f"{result.tasks_per_second:>7.3f}  {result.samples_per_second:>9.1f}  {per_node:>14}  "
        f"{result.task_seconds:>10.2f}  {result.own_cores:>9.2f}  {result.background_cores:>10.2f}  "
        f"{result.load_before} -> {result.load_after}",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=Path, default=REPO_ROOT / "examples" / "builtin.txt")
    parser.add_argument("--first", type=int, default=None, help="Time only the first N objects of the file.")
    parser.add_argument("--rotations", type=int, default=2)
    parser.add_argument("--refiner", default="none", help="Refiner of the timed jobs (default none).")
    parser.add_argument("--nodes", type=int, nargs="+", default=[1, 2, 3], help="Worker node counts (1 CPU each).")
    args = parser.parse_args()
    config = GenerationConfig(rotations=args.rotations, refiner=args.refiner)
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory(prefix="datagen-cluster-") as scratch:
        folder = Path(scratch)
        objects = objects_file(args.objects, args.first, folder)
        count = len(read_objects_file(objects).objects)
        print(
            f"{count} objects of {args.objects} x {args.rotations} rotations, refiner {args.refiner} "
            f"(config hash {config.config_hash()[:12]}); head 0 CPUs + N worker nodes of 1 CPU; "
            f"machine: {cores} cores, loadavg {loadavg()}; cluster start-up and warm-up excluded",
            flush=True,
        )
        if max(args.nodes) > cores:
            print(f"note: {cores} cores: no gain is expected past {cores} nodes (they share the cores)", flush=True)
        print(
            "nodes  tasks  samples   wall s  tasks/s  samples/s  tasks per node  task CPU-s  own cores  background  "
            "loadavg before -> after",
            flush=True,
        )
        results = []
        for nodes in sorted(set(args.nodes)):
            results.append(run(nodes, objects, config, folder))
            report(results[-1])
    print(
        "task CPU-s: mean of each task's timed steps (shard metadata); own cores: this process tree's CPU time "
        "over the wall time; background: the other processes' busy CPU (/proc/stat minus own), in cores"
    )
    base = next((r for r in results if r.nodes == 1), None)
    if base is None:
        return
    for result in results:
        if result.nodes == 1:
            continue
        print(
            f"scaling {result.nodes} nodes / 1 node: tasks/s {result.tasks_per_second / base.tasks_per_second:.2f}x, "
            f"samples/s {result.samples_per_second / base.samples_per_second:.2f}x (ideal {result.nodes}x"
            f"{'' if result.nodes <= cores else f'; at most {cores}x on {cores} cores'})",
            flush=True,
        )


if __name__ == "__main__":
    main()
