"""The compose cluster at scale (issue 40, item 3): jobs driven from the host against docker-compose.yml.

    bash scripts/cluster-up.sh      # head (datagen serve), 2 Ray workers, SeaweedFS S3; .env beside
    python -m benchmarks.scale.cluster engine --tasks 10000 --work /work/runs/cluster/engine
    python -m benchmarks.scale.cluster real --objects DIR/objects.txt --config real.toml \\
        --work /work/runs/cluster/real

Both read the S3 port, credentials and bucket, and the Ray client port, from ``.env`` (never printed),
and set the standard AWS variables for themselves and the commands they start.

``engine``: the 10k-task engine case on the cluster. ``datagen submit --detach`` of N/8 synthetic
meshes at 8 rotations (``objects synth --seed 0``) with ``--out s3://BUCKET/...`` (the host's ledger),
then the driver (``drive``, a process of its own) runs the job over Ray client
(``RunSettings(ray_address=ray://127.0.0.1:PORT)``) with ``datagen.engine.worker.empty_task`` as the
task body, as `benchmarks.scale.drive` does on a local Ray: CPU and wall per task, peak memory, the
progress every 1 % and the end of the job (``finalise``: from the last task recorded to the return of
`datagen.api.resume`). The containers' CPU over the run comes from their cgroups (cgroup v1
``cpuacct.usage``). Then ``datagen status JOB``.

``real``: a real job, once on a local Ray (``datagen submit --workers 2`` to a local folder: the
reference) and once from the host on the cluster (``datagen submit --address ray://...`` to S3), with two
faults in the cluster run: at ``--kill-container-at`` of the tasks done, SIGKILL from the host to the
first worker container's init (as a crash or the OOM killer would; the restart policy brings it back
and it rejoins), and at ``--kill-worker-at`` SIGKILL to a Ray worker process running a task in the
second worker container. The job must end complete; ``datagen shards validate`` and
``datagen shards digest`` of both datasets are compared. The meshes are copied into every worker
container at the same absolute path first (a cluster needs the objects file's paths on every node: a
shared file system; datagen reads meshes from local paths only).

Each writes ``WORK/summary.json`` and prints it; the figures in benchmarks/scale/results/cluster.md come
from there.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT
from benchmarks.scale.measure import Measurement, machine_line, run_measured

JOB_ID = re.compile(r"\d{8}-\d{6}-[0-9a-f]{6}")
ENGINE_CONFIG = 'rotations = 8\nrefiner = "none"\n'


# ---------------------------------------------------------------------------------------------------------
# the cluster: its .env, containers and cgroups
# ---------------------------------------------------------------------------------------------------------


def read_env_file(path: Path) -> dict[str, str]:
    values: dict[str, str] = {}
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if line and not line.startswith("#") and "=" in line:
            key, _, value = line.partition("=")
            values[key.strip()] = value.strip().strip('"').strip("'")
    return values


def cluster_env(env_file: Path) -> tuple[dict[str, str], str, str]:
    """(this process's environment with the AWS variables of the cluster's S3, the Ray client
    address, the bucket)."""
    values = read_env_file(env_file)
    env = dict(os.environ)
    env.update(
        AWS_ENDPOINT_URL=f"http://127.0.0.1:{values.get('S3_PORT', '8333')}",
        AWS_ACCESS_KEY_ID=values["S3_ACCESS_ID"],
        AWS_SECRET_ACCESS_KEY=values["S3_SECRET_KEY"],
        AWS_DEFAULT_REGION=values.get("AWS_DEFAULT_REGION", "us-east-1"),
        OPENBLAS_NUM_THREADS="1",
    )
    env.pop("RAY_ADDRESS", None)
    address = f"ray://127.0.0.1:{values.get('RAY_CLIENT_PORT', '10001')}"
    return env, address, values.get("DATAGEN_BUCKET", "datasets")


def podman(*args: str, check: bool = True) -> str:
    done = subprocess.run(["podman", *args], capture_output=True, text=True, check=False)
    if check and done.returncode != 0:
        raise RuntimeError(f"podman {' '.join(args)}: {done.stderr.strip()}")
    return done.stdout.strip()


def containers(project: str = "datagen") -> list[str]:
    names = podman("ps", "--format", "{{.Names}}", "--filter", f"label=com.docker.compose.project={project}")
    return sorted(names.split())


def container_cpu_seconds(name: str) -> float | None:
    """CPU seconds the container's cgroup has used since it (re)started (cgroup v1 cpuacct)."""
    path = podman("inspect", "--format", "{{.State.CgroupPath}}", name, check=False)
    for root in ("/sys/fs/cgroup/cpuacct", "/sys/fs/cgroup/cpu,cpuacct"):
        usage = Path(root + path) / "cpuacct.usage"
        if path and usage.exists():
            return int(usage.read_text()) / 1e9
    unified = Path("/sys/fs/cgroup" + path) / "cpu.stat"
    if path and unified.exists():
        for line in unified.read_text().splitlines():
            if line.startswith("usage_usec"):
                return int(line.split()[1]) / 1e6
    return None


def cpu_snapshot() -> dict[str, float | None]:
    return {name: container_cpu_seconds(name) for name in containers()}


def cpu_delta(before: dict[str, float | None], after: dict[str, float | None]) -> dict[str, float | None]:
    """Per container, CPU seconds between two snapshots (None where it restarted: its counter began again)."""
    delta: dict[str, float | None] = {}
    for name, end in after.items():
        start = before.get(name)
        delta[name] = None if start is None or end is None or end < start else round(end - start, 2)
    return delta


def ray_worker_nodes(head: str = "datagen_head_1") -> set[str] | None:
    """The ids of the Ray nodes with CPUs the head counts alive (None when the head did not answer)."""
    code = (
        "import logging, ray\n"
        "ray.init(address='auto', logging_level=logging.ERROR, log_to_driver=False)\n"
        "print(*[n['NodeID'] for n in ray.nodes() if n['Alive'] and n['Resources'].get('CPU', 0) > 0])"
    )
    out = podman("exec", head, "python", "-c", code, check=False)
    return set(out.splitlines()[-1].split()) if out else None


def ray_workers_alive(head: str = "datagen_head_1") -> int:
    nodes = ray_worker_nodes(head)
    return -1 if nodes is None else len(nodes)


def failed_ray_attempts(head: str = "datagen_head_1") -> list[dict[str, Any]]:
    """Task attempts Ray recorded as failed (the state API on the head): task id, attempt, error type."""
    out = podman(
        "exec",
        head,
        "ray",
        "list",
        "tasks",
        "--filter",
        "state=FAILED",
        "--detail",
        "--format",
        "json",
        "--limit",
        "10000",
        check=False,
    )
    try:
        rows = json.loads(out[out.index("[") :]) if "[" in out else []
    except ValueError:
        return []
    keys = ("task_id", "attempt_number", "error_type", "node_id", "name")
    return [{key: row.get(key) for key in keys} for row in rows]


def started_at(name: str) -> str:
    return podman("inspect", "--format", "{{.State.StartedAt}}", name, check=False)


# ---------------------------------------------------------------------------------------------------------
# the host's ledger
# ---------------------------------------------------------------------------------------------------------


def ledger_counts(home: Path, job: str) -> dict[str, int]:
    with sqlite3.connect(home / "ledger.db", timeout=30) as db:
        rows = db.execute("SELECT state, COUNT(*) FROM tasks WHERE job_id = ? GROUP BY state", (job,)).fetchall()
    return {state: int(n) for state, n in rows}


def ledger_attempts(home: Path, job: str) -> tuple[int, int, dict[str, int]]:
    """(tasks, attempts summed over them, done tasks per worker container host)."""
    with sqlite3.connect(home / "ledger.db", timeout=30) as db:
        tasks, attempts = db.execute("SELECT COUNT(*), SUM(attempts) FROM tasks WHERE job_id = ?", (job,)).fetchone()
        placements = db.execute("SELECT placement FROM tasks WHERE job_id = ? AND state = 'done'", (job,)).fetchall()
    hosts: dict[str, int] = {}
    nodes: set[str] = set()
    for (placement,) in placements:
        node, _, host = (placement or "?@?").partition("@")
        hosts[host] = hosts.get(host, 0) + 1
        nodes.add(node)
    hosts["distinct Ray nodes"] = len(nodes)
    return int(tasks), int(attempts or 0), hosts


def job_id_in(path: Path, timeout: float = 300.0) -> str:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        found = JOB_ID.search(path.read_text()) if path.exists() else None
        if found:
            return found.group(0)
        time.sleep(0.3)
    raise RuntimeError(f"no job id in {path}")


def datagen() -> str:
    return str(Path(sys.executable).with_name("datagen"))


def submit_args(objects: Path, config: Path, out: str, home: Path, *extra: str) -> list[str]:
    """`datagen submit` of ``objects`` under ``config`` into ``out`` with its own ledger ``home``."""
    return [
        datagen(),
        "submit",
        "--objects",
        str(objects),
        "--config",
        str(config),
        "--out",
        out,
        "--home",
        str(home),
        *extra,
    ]


def measured(args: list[str], env: dict[str, str], log: Path, **options: Any) -> Measurement:
    print(f"== {' '.join(args[:3])} ... > {log}", flush=True)
    result = run_measured(args, cwd=REPO_ROOT, env=env, stdout=log, **options)
    print(f"   rc {result.rc}, {result.wall:.1f} s wall, {result.cpu:.1f} CPU s, {result.peak_mb:.0f} MiB", flush=True)
    if result.rc != 0:
        raise RuntimeError(f"{args[:3]} failed ({result.rc}): {log.read_text()[-2000:]}")
    return result


def digest(url: str, env: dict[str, str], log: Path) -> tuple[Measurement, list[str]]:
    result = measured([datagen(), "shards", "digest", url], env, log)
    return result, log.read_text().split()


# ---------------------------------------------------------------------------------------------------------
# engine: N empty tasks over Ray client
# ---------------------------------------------------------------------------------------------------------


def engine(args: argparse.Namespace) -> dict[str, Any]:
    env, address, bucket = cluster_env(args.env_file)
    work: Path = args.work
    work.mkdir(parents=True, exist_ok=True)
    lines = args.tasks // 8
    synth = work / f"synth-{lines}"
    if not (synth / "objects.txt").exists():
        measured(
            [datagen(), "objects", "synth", "--count", str(lines), "--seed", "0", "--out", str(synth)],
            env,
            work / "synth.log",
        )
    config = work / "engine.toml"
    config.write_text(ENGINE_CONFIG)
    run = time.strftime("%Y%m%d-%H%M%S")
    home = work / f"home-{run}"
    out = f"s3://{bucket}/scale-cluster/{run}/engine-{args.tasks}"
    summary: dict[str, Any] = {"machine": machine_line(), "tasks": args.tasks, "out": out, "address": address}
    summary["containers"] = containers()
    summary["ray_workers"] = ray_workers_alive()
    enqueue = measured(
        [
            datagen(),
            "submit",
            "--detach",
            "--objects",
            str(synth / "objects.txt"),
            "--config",
            str(config),
            "--out",
            out,
            "--home",
            str(home),
        ],
        env,
        work / "enqueue.log",
    )
    job = job_id_in(work / "enqueue.log")
    summary.update(job=job, enqueue=enqueue.to_json())
    report = work / f"drive-{run}.json"
    before = cpu_snapshot()
    drive = measured(
        [
            sys.executable,
            "-m",
            "benchmarks.scale.cluster",
            "drive",
            "--home",
            str(home),
            "--job",
            job,
            "--address",
            address,
            "--report",
            str(report),
        ],
        env,
        work / "drive.log",
        report=report,
    )
    summary["containers_cpu_s"] = cpu_delta(before, cpu_snapshot())
    summary["drive"] = drive.to_json()
    summary["counts"] = ledger_counts(home, job)
    status = measured([datagen(), "status", job, "--home", str(home)], env, work / "status.log")
    summary["status_job"] = status.to_json()
    return summary


def drive(args: argparse.Namespace) -> None:
    """One driver run over Ray client with the empty task body (run by ``engine`` in its own process)."""
    from datagen import api
    from datagen.engine.driver import JobProgress, ensure_ray
    from datagen.engine.worker import empty_task
    from datagen.settings import RunSettings

    def cpu_seconds() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    def resident_mb() -> float:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return 0.0

    started = time.perf_counter()
    ensure_ray(args.address, None)
    report: dict[str, Any] = {"connect_s": time.perf_counter() - started, "rss_before_mb": resident_mb()}
    curve: list[tuple[float, float, int]] = []
    marks: dict[str, float] = {}
    step = 0

    def progress(state: JobProgress) -> None:
        nonlocal step
        now = time.perf_counter() - t0
        finished = state.done + state.failed
        marks.setdefault("first_tick_s", now)
        if not step:
            step = max(1, state.total // 100)
        if finished >= state.total and "all_recorded_s" not in marks:
            marks["all_recorded_s"] = now
            marks["all_recorded_cpu_s"] = cpu_seconds() - cpu0
        if not curve or finished >= curve[-1][2] + step:
            curve.append((now, cpu_seconds() - cpu0, finished))

    t0, cpu0 = time.perf_counter(), cpu_seconds()
    settings = RunSettings(home=args.home, ray_address=args.address)
    job = api.resume(args.job, settings, progress, body=empty_task)
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - cpu0
    report.update(
        state=job.state,
        summary={k: v for k, v in (job.summary or {}).items() if k in ("tasks", "done", "failed", "samples", "swept")},
        run_wall_s=wall,
        run_cpu_s=cpu,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        curve=curve,
        **marks,
    )
    if "all_recorded_s" in marks:
        report["finalise_wall_s"] = wall - marks["all_recorded_s"]
        report["finalise_cpu_s"] = cpu - marks["all_recorded_cpu_s"]
    args.report.write_text(json.dumps(report))


# ---------------------------------------------------------------------------------------------------------
# real: a real job on a local Ray and on the cluster with faults; the digests compared
# ---------------------------------------------------------------------------------------------------------


def stage_meshes(objects: Path, workers: list[str]) -> float:
    """Copy the objects file's folder into every worker container at the same absolute path."""
    started = time.perf_counter()
    folder = objects.resolve().parent
    for name in workers:
        podman("exec", "-u", "root", name, "mkdir", "-p", str(folder.parent))
        podman("cp", str(folder), f"{name}:{folder.parent}")
        podman("exec", "-u", "root", name, "chmod", "-R", "a+rX", str(folder))
    return time.perf_counter() - started


def busy_ray_worker(container: str, timeout: float = 60.0) -> tuple[int, str]:
    """(host pid, title) of a Ray worker process of ``container`` running a task now: the processes of a
    rootful podman container are the host's, found by their cgroup (the container's id) and their title
    (Ray names a worker ``ray::FUNCTION`` while it runs a task, ``ray::IDLE`` between tasks). Scanning
    /proc on the host lets the caller kill within microseconds of seeing the task run (a task here
    takes a few tenths of a second)."""
    ident = podman("inspect", "--format", "{{.Id}}", container)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                title = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
                if title.startswith("ray::_remote_execute") and ident in (entry / "cgroup").read_text():
                    return int(entry.name), title
            except OSError:
                continue
        time.sleep(0.02)
    raise RuntimeError(f"no Ray worker running a task in {container} within {timeout:.0f} s")


def real(args: argparse.Namespace) -> dict[str, Any]:
    env, address, bucket = cluster_env(args.env_file)
    work: Path = args.work
    work.mkdir(parents=True, exist_ok=True)
    objects, config = args.objects.resolve(), args.config.resolve()
    summary: dict[str, Any] = {"machine": machine_line(), "objects": str(objects), "config": config.read_text()}
    workers = [name for name in containers() if "_worker_" in name]
    summary["stage_s"] = stage_meshes(objects, workers)

    local = work / "local"
    if not (work / "local.json").exists():
        run = measured(
            submit_args(objects, config, str(local), work / "local-home", "--workers", str(args.local_workers)),
            env,
            work / "local.log",
        )
        digest_run, words = digest(str(local), env, work / "local.digest")
        (work / "local.json").write_text(
            json.dumps({"run": run.to_json(), "digest": words[:3], "digest_run": digest_run.to_json()})
        )
    summary["local"] = json.loads((work / "local.json").read_text())

    run_id = time.strftime("%Y%m%d-%H%M%S")
    home, out = work / f"cluster-home-{run_id}", f"s3://{bucket}/scale-cluster/{run_id}/real"
    log = work / f"cluster-{run_id}.log"
    result: dict[str, Measurement] = {}
    before = cpu_snapshot()
    starts = {name: started_at(name) for name in containers()}
    failed_before = failed_ray_attempts()

    def submit() -> None:
        result["run"] = run_measured(
            submit_args(objects, config, out, home, "--address", address),
            cwd=REPO_ROOT,
            env=env,
            stdout=log,
        )

    print(f"== cluster job -> {out} (log {log})", flush=True)
    started = time.perf_counter()
    thread = threading.Thread(target=submit)
    thread.start()
    job = job_id_in(log)
    total = sum(ledger_counts(home, job).values())
    faults: list[dict[str, Any]] = []

    def wait_done(share: float) -> int:
        while thread.is_alive():
            done = ledger_counts(home, job).get("done", 0)
            if done >= share * total:
                return done
            time.sleep(0.2)
        raise RuntimeError(f"the job ended before {share:.0%} of its tasks were done: {log.read_text()[-2000:]}")

    first, second = workers[0], workers[-1]
    watcher: threading.Thread | None = None
    if args.kill_container_at > 0:
        done = wait_done(args.kill_container_at)
        nodes_before = ray_worker_nodes() or set()
        pid = int(podman("inspect", "--format", "{{.State.Pid}}", first))
        inner, title = busy_ray_worker(first)  # a container that runs a task: that task must be run again
        os.kill(pid, 9)
        killed_at = time.perf_counter()
        fault: dict[str, Any] = {
            "what": f"SIGKILL from the host to {first}'s init (host pid {pid}), while its Ray worker process "
            f"(host pid {inner}) ran a task ({title!r}): the whole container dies, raylet and task with it",
            "at_done": done,
            "at_s": killed_at - started,
        }
        print(f"   killed {first} at {done}/{total} done", flush=True)
        # the container comes back by its restart policy; its raylet joins the head as a new node
        while thread.is_alive() and "running_again_s" not in fault:
            state = podman("inspect", "--format", "{{.State.Running}} {{.State.Pid}}", first, check=False).split()
            if state[:1] == ["true"] and state[1:] != [str(pid)]:
                fault["running_again_s"] = time.perf_counter() - killed_at
            time.sleep(0.5)
        faults.append(fault)

        def rejoin() -> None:  # until the head counts a new node with CPUs (each look: a process on the head)
            while thread.is_alive():
                nodes = ray_worker_nodes()
                if nodes is not None and nodes - nodes_before:
                    fault["new_node_joined_after_s"] = time.perf_counter() - killed_at
                    return
                time.sleep(2.0)

        watcher = threading.Thread(target=rejoin, daemon=True)
        watcher.start()

    if args.kill_worker_at > 0:
        done = wait_done(args.kill_worker_at)
        inner, title = busy_ray_worker(second)
        os.kill(inner, 9)
        faults.append(
            {
                "what": f"SIGKILL to the Ray worker process running a task in {second} (host pid {inner}, {title!r})",
                "at_done": done,
                "at_s": time.perf_counter() - started,
            }
        )
        print(f"   killed a Ray worker process ({title}) in {second} at {done}/{total} done", flush=True)
    thread.join()
    if watcher is not None:
        watcher.join()
    failed_after = failed_ray_attempts()
    summary["ray_failed_attempts"] = [row for row in failed_after if row not in failed_before]
    summary["restarted"] = [name for name, at in starts.items() if started_at(name) != at]
    run = result["run"]
    summary["containers_cpu_s"] = {
        name: None if name in summary["restarted"] else cpu for name, cpu in cpu_delta(before, cpu_snapshot()).items()
    }
    summary["cluster"] = {"job": job, "out": out, "run": run.to_json(), "tail": log.read_text()[-1500:]}
    summary["faults"] = faults
    summary["job_end_after_kills_s"] = [run.wall - fault["at_s"] for fault in faults]
    tasks, attempts, hosts = ledger_attempts(home, job)
    summary["ledger"] = {"counts": ledger_counts(home, job), "tasks": tasks, "attempts": attempts, "done_by": hosts}
    if run.rc != 0:
        raise RuntimeError(f"the cluster job failed ({run.rc}): {log.read_text()[-2000:]}")
    summary["validate"] = measured(
        [datagen(), "shards", "validate", out], env, work / f"validate-{run_id}.log"
    ).to_json() | {"tail": (work / f"validate-{run_id}.log").read_text()[-600:]}
    digest_run, words = digest(out, env, work / f"cluster-{run_id}.digest")
    summary["cluster"]["digest"] = words[:3]
    summary["cluster"]["digest_run"] = digest_run.to_json()
    summary["same_digest"] = words[0] == summary["local"]["digest"][0]
    summary["ray_workers_after"] = ray_workers_alive()
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-file", type=Path, default=REPO_ROOT / ".env")
    commands = parser.add_subparsers(dest="command", required=True)
    one = commands.add_parser("engine", help="N empty tasks on the cluster from the host")
    one.add_argument("--tasks", type=int, default=10_000)
    one.add_argument("--work", type=Path, required=True)
    two = commands.add_parser("drive", help="(internal) one driver run over Ray client, empty task body")
    two.add_argument("--home", type=Path, required=True)
    two.add_argument("--job", required=True)
    two.add_argument("--address", required=True)
    two.add_argument("--report", type=Path, required=True)
    three = commands.add_parser("real", help="a real job locally and on the cluster with faults; digests")
    three.add_argument("--objects", type=Path, required=True)
    three.add_argument("--config", type=Path, required=True)
    three.add_argument("--work", type=Path, required=True)
    three.add_argument("--local-workers", type=int, default=2)
    three.add_argument("--kill-container-at", type=float, default=0.3, help="share of tasks done (0: no kill)")
    three.add_argument("--kill-worker-at", type=float, default=0.6, help="share of tasks done (0: no kill)")
    args = parser.parse_args()
    if args.command == "drive":
        drive(args)
        return
    summary = engine(args) if args.command == "engine" else real(args)
    path = args.work / f"summary-{time.strftime('%Y%m%d-%H%M%S')}.json"
    path.write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    print(f"summary: {path}")


if __name__ == "__main__":
    main()
