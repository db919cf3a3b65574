"""One driver run for the engine's scale benchmark: `datagen resume JOB` with the empty task body.

Run by path, in a process of its own, by `benchmarks.scale.engine` (not as a module: the source tree
it measures, maybe an older worktree, comes first on PYTHONPATH and need not have this package)::

    python benchmarks/scale/drive.py --home HOME --job JOB --workers 2 --report OUT.json

It starts a local Ray first (not counted), then runs what `datagen resume` runs (`datagen.api.resume`:
reopen the job, then `run_job`) with `datagen.engine.worker.empty_task` as the body, so what is
measured is the driver, the ledger and Ray's scheduling alone. It writes to ``--report``: the run's
wall and this process's CPU seconds (the driver, with Ray's threads in it), its peak resident set,
its resident set before the run, and the progress every 1 % of the tasks (so a per-task cost that
grows during the run shows). On SIGINT (the benchmark's deadline) it stops and reports how far it got.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path
from typing import Any


def resident_mb() -> float:
    """This process's resident set now, MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def forget_own_folder() -> None:
    """Run by path, this folder comes first on sys.path, and the modules beside this one (a
    ``storage.py``) would shadow the packages measured; drop it before importing them."""
    here = Path(__file__).resolve().parent
    sys.path[:] = [entry for entry in sys.path if Path(entry or ".").resolve() != here]


def main() -> None:
    forget_own_folder()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--home", type=Path, required=True)
    parser.add_argument("--job", required=True)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report", type=Path, required=True)
    args = parser.parse_args()

    from datagen import api
    from datagen.engine.driver import JobProgress, ensure_ray
    from datagen.engine.worker import empty_task
    from datagen.settings import RunSettings

    started = time.perf_counter()
    ensure_ray(None, args.workers)
    ray_seconds = time.perf_counter() - started
    before_mb = resident_mb()
    curve: list[tuple[float, float, int]] = []
    ticks = 0
    step = 0

    def progress(state: JobProgress) -> None:
        nonlocal ticks, step
        ticks += 1
        if not step:
            step = max(1, state.total // 100)
        finished = state.done + state.failed
        if not curve or finished >= curve[-1][2] + step:
            curve.append((time.perf_counter() - t0, cpu_seconds() - cpu0, finished))

    report: dict[str, Any] = {"ray_start_s": ray_seconds, "rss_before_mb": before_mb}
    t0, cpu0 = time.perf_counter(), cpu_seconds()
    try:
        job = api.resume(args.job, RunSettings(home=args.home, num_workers=args.workers), progress, body=empty_task)
        report.update(state=job.state, summary_tasks=(job.summary or {}).get("tasks"))
    except KeyboardInterrupt:
        report.update(state="stopped")
    report.update(
        run_wall_s=time.perf_counter() - t0,
        run_cpu_s=cpu_seconds() - cpu0,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        ticks=ticks,
        curve=curve,
        finished=curve[-1][2] if curve else 0,
    )
    args.report.write_text(json.dumps(report))


if __name__ == "__main__":
    main()
