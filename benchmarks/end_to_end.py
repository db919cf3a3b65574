"""Benchmark: whole jobs through the engine on a local Ray, with 1 and with 2 worker CPUs.

    python benchmarks/end_to_end.py [--objects examples/builtin.txt] [--rotations 2] [--cpus 1 2]

For each worker-CPU count it starts a private local Ray (`datagen.engine.driver.ensure_ray`), runs a small
warm-up job (so worker processes are started and have imported the pipeline), then times one job of
every object of the objects file (default: the 22 built-ins) x ``--rotations`` rotations (default 2,
to keep it short; otherwise the default generation config) through `datagen.api.submit`, and prints:

- tasks, samples, wall seconds, tasks/s and samples/s (Ray start-up and warm-up excluded);
- CPU-s/task: the mean of each task's own timed steps (shard metadata ``seconds``: scan + refine +
  label, single-threaded), and the worker processes' CPU time (/proc utime + stime) per task;
- the cores this benchmark's process tree (driver, Ray, workers) actually got: its CPU time over the
  wall time;
- the machine's load while it ran: /proc/loadavg before and after, and the background load, i.e. the
  machine's busy CPU time (/proc/stat) minus this benchmark's own process tree, in cores;
- the scaling ratio of tasks/s (2 CPUs over 1; the target is >= 1.8x on a quiet machine).

Linux only (reads /proc). Single-threaded BLAS in every worker.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"
os.environ.pop("RAY_ADDRESS", None)

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

from datagen import api  # noqa: E402
from datagen.engine.driver import ensure_ray  # noqa: E402
from datagen.settings import RunSettings  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402
from storage import (  # noqa: E402
    ShardReader,
    committed_tasks,
    open_location,
)

REPO_ROOT = Path(__file__).resolve().parents[1]
TICKS = os.sysconf("SC_CLK_TCK")
WARM_UP_OBJECTS = ("builtin:capsule", "builtin:cone")


# ---------------------------------------------------------------------------------------------------------
# /proc
# ---------------------------------------------------------------------------------------------------------


def machine_busy_ticks() -> int:
    """Busy jiffies of all CPUs since boot: user + nice + system + irq + softirq + steal."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return user + nice + system + irq + softirq + steal


def loadavg() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def process_table() -> dict[int, tuple[int, int, str]]:
    """pid -> (ppid, utime + stime ticks, cmdline) of every readable process."""
    table = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        table[int(entry)] = (int(fields[1]), int(fields[11]) + int(fields[12]), cmdline.strip())
    return table


def own_tree(table: dict[int, tuple[int, int, str]]) -> dict[int, tuple[int, str]]:
    """This process and its descendants (Ray's GCS, raylet, agents, workers): pid -> (ticks, cmdline)."""
    children: dict[int, list[int]] = {}
    for pid, (ppid, _, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    tree, stack = {}, [os.getpid()]
    while stack:
        pid = stack.pop()
        if pid in table:
            tree[pid] = (table[pid][1], table[pid][2])
        stack.extend(children.get(pid, []))
    return tree


def is_task_worker(cmdline: str) -> bool:
    return cmdline.startswith(("ray::IDLE", "ray::_remote_execute")) or "default_worker.py" in cmdline


@dataclass(frozen=True)
class Snapshot:
    wall: float
    machine: int
    tree: dict[int, tuple[int, str]]
    load: str

    @staticmethod
    def take() -> Snapshot:
        return Snapshot(time.perf_counter(), machine_busy_ticks(), own_tree(process_table()), loadavg())


def tree_delta(before: Snapshot, after: Snapshot, workers_only: bool = False) -> float:
    """CPU seconds used between two snapshots by this process tree (or only its Ray task workers)."""
    total = 0
    for pid, (ticks, cmdline) in after.tree.items():
        if workers_only and not is_task_worker(cmdline):
            continue
        total += ticks - before.tree.get(pid, (0, ""))[0]
    return total / TICKS


# ---------------------------------------------------------------------------------------------------------
# runs
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Result:
    cpus: int
    tasks: int
    samples: int
    wall: float
    task_seconds: list[float]
    worker_cpu: float
    own_cpu: float
    background_cores: float
    load_before: str
    load_after: str


def task_seconds(url: str) -> list[float]:
    """Each committed task's own compute seconds (its timed steps, from the shard metadata)."""
    location = open_location(url)
    seconds = []
    for record in committed_tasks(location):
        meta = ShardReader(location, record.shard).attributes.metadata
        seconds.append(float(sum(meta["seconds"].values())))
    return seconds


def run(cpus: int, objects: Path, config: GenerationConfig, folder: Path) -> Result:
    import ray

    if ray.is_initialized():
        ray.shutdown()
    ensure_ray(None, cpus)
    try:
        warm = folder / f"warm-{cpus}"
        warm_objects = warm / "objects.txt"
        warm.mkdir(parents=True)
        warm_objects.write_text("\n".join(WARM_UP_OBJECTS) + "\n")
        warm_config = config.model_copy(update={"rotations": max(1, cpus)})
        api.submit(warm_objects, warm_config, RunSettings(home=warm, num_workers=cpus, ray_address=None))

        settings = RunSettings(home=folder / f"run-{cpus}", num_workers=cpus, ray_address=None)
        before = Snapshot.take()
        job = api.submit(objects, config, settings)
        after = Snapshot.take()
    finally:
        ray.shutdown()
    if job.state != "done":
        raise SystemExit(f"job {job.job_id} ended {job.state}: {job.summary}")
    summary = job.summary or {}
    wall = after.wall - before.wall
    own = tree_delta(before, after)
    machine = (after.machine - before.machine) / TICKS
    return Result(
        cpus=cpus,
        tasks=int(summary.get("done", 0)),
        samples=int(summary.get("samples", 0)),
        wall=wall,
        task_seconds=task_seconds(job.out),
        worker_cpu=tree_delta(before, after, workers_only=True),
        own_cpu=own,
        background_cores=max(0.0, machine - own) / wall,
        load_before=before.load,
        load_after=after.load,
    )


def report(result: Result) -> None:
    per_task = statistics.fmean(result.task_seconds) if result.task_seconds else float("nan")
    print(
        f"{result.cpus:>4}  {result.tasks:>5}  {result.samples:>7}  {result.wall:>7.1f}  "
        f"{result.tasks / result.wall:>7.2f}  {result.samples / result.wall:>9.1f}  "
        f"{per_task:>10.2f}  {result.worker_cpu / max(1, result.tasks):>12.2f}  {result.own_cpu:>9.1f}  "
        f"{result.own_cpu / result.wall:>9.2f}  {result.background_cores:>10.2f}  "
        f"{result.load_before} -> {result.load_after}",
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=Path, default=REPO_ROOT / "examples" / "builtin.txt")
    parser.add_argument("--rotations", type=int, default=2)
    parser.add_argument("--cpus", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    config = GenerationConfig(rotations=args.rotations)
    print(
        f"objects {args.objects} x rotations {args.rotations} (config hash {config.config_hash()[:12]}); "
        f"machine: {os.cpu_count()} CPUs; Ray start-up and a warm-up job excluded from the timings",
        flush=True,
    )
    print(
        "cpus  tasks  samples   wall s  tasks/s  samples/s  task CPU-s  worker CPU-s  own CPU-s  "
        "own cores  background  loadavg before -> after",
        flush=True,
    )
    results = []
    with tempfile.TemporaryDirectory(prefix="datagen-e2e-") as folder:
        for cpus in args.cpus:
            results.append(run(cpus, args.objects, config, Path(folder)))
            report(results[-1])
    print(
        "task CPU-s: mean per task of its timed steps (shard metadata); worker CPU-s: Ray task workers' "
        "utime+stime per task; own CPU-s / own cores: this benchmark's whole process tree (CPU-s, and over "
        "the wall time); background: other processes' busy CPU (/proc/stat minus own), in cores"
    )
    by_cpus = {r.cpus: r for r in results}
    if 1 in by_cpus and 2 in by_cpus:
        ratio = (by_cpus[2].tasks / by_cpus[2].wall) / (by_cpus[1].tasks / by_cpus[1].wall)
        noisy = max(by_cpus[1].background_cores, by_cpus[2].background_cores)
        verdict = "meets" if ratio >= 1.8 else "below"
        target = f"{verdict} the 1.8x target; background load up to {noisy:.2f} cores"
        print(f"scaling 2 CPUs / 1 CPU: {ratio:.2f}x ({target})")


if __name__ == "__main__":
    main()
