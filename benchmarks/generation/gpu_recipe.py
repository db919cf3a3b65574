"""Benchmark: the first osvp recipe's training set made on a GPU and on the CPU, timed, every label compared.

    python -m benchmarks.generation.gpu_recipe --work W [--device cuda] [--objects-count 40] \\
        [--workers 16] [--config FILE] [--budget 240] [--out benchmarks/generation/results/gpu-recipe.md]

Issue 41's check of a node with a GPU: the recipe's objects (`recipe_time.recipe_objects`: the 22
built-ins, 11 seeded synthetic shapes and the 7 shared meshes there are; ``--objects-count N`` keeps
the first N when time is short, and the report says so) at the config's rotations, made twice by
`datagen submit` as a user makes them, each its own ledger and dataset under ``--work``:

- ``device``: ``--refiner-gpus`` 1 / ``--workers`` (the tasks share the GPU), on ``--device cuda``;
  with ``--shared-refiner`` one host holds the network on the GPU and runs every task's jobs
  (``--refiner-batch`` jobs per encoder call), the tasks reserving no GPU;
- ``cpu``: the same job with the refiner on the CPU, every core a worker.

Each job is stopped at ``--budget`` seconds (SIGINT: the job is cancelled, what was committed stays)
and timed from launch to exit. Then the two datasets are read side by side (`storage.open_dataset`):
the samples both hold, matched by sample id, and how many have the same label, the same view state
and the same refined point count |P(O_S)|; the samples only one holds (a job that ran out of time).
The tasks' CPU seconds per step come from each dataset's commit records. ``--device cpu`` runs both
jobs on the CPU: every label must then agree, which is how the tests check this script without a GPU.
The report is printed, and written to ``--out`` when given (a new file: an existing one is refused
unless ``--replace``).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.common import REPO_ROOT, interruptible_child
from benchmarks.generation.recipe_time import recipe_objects

INTERRUPT_GRACE = 60.0
"""Seconds a job stopped at its budget may take to cancel and exit before it is killed."""


@dataclass(frozen=True)
class Job:
    """One timed `datagen submit` and what its dataset holds."""

    label: str
    wall: float
    stopped: bool
    tasks: int
    samples: int
    step_cpu: dict[str, float] = field(default_factory=dict)
    task_cpu: float = 0.0


@dataclass(frozen=True)
class Agreement:
    """The two datasets' samples, matched by sample id."""

    common: int
    only_device: int
    only_cpu: int
    same_label: int
    same_view_state: int
    same_points: int


def submit_command(
    objects: Path, out: Path, config: Path | None, workers: int, gpus: float, shared: bool = False, batch: int = 1
) -> list[str]:
    command = [sys.executable, "-m", "datagen.cli.main", "submit", "--objects", str(objects), "--out", str(out)]
    command += ["--workers", str(workers)]
    if config is not None:
        command += ["--config", str(config)]
    if gpus > 0:
        command += ["--refiner-gpus", f"{gpus:g}"]
    if shared:
        command += ["--shared-refiner", "--refiner-batch", str(batch)]
    return command


def run_job(label: str, command: list[str], work: Path, budget: float | None) -> tuple[float, bool]:
    """Run one job in its own home under ``work`` with its output in ``work/LABEL.log``; (wall, stopped)."""
    env = {**os.environ, "DATAGEN_HOME": str(work / f"home-{label}"), "OPENBLAS_NUM_THREADS": "1"}
    env.pop("RAY_ADDRESS", None)
    started = time.perf_counter()
    with (work / f"{label}.log").open("wb") as log:
        process = subprocess.Popen(
            command, cwd=REPO_ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, preexec_fn=interruptible_child
        )
        try:
            process.wait(timeout=budget)
            return time.perf_counter() - started, False
        except subprocess.TimeoutExpired:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=INTERRUPT_GRACE)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            return time.perf_counter() - started, True


def dataset_job(label: str, url: Path, wall: float, stopped: bool) -> Job:
    """What the dataset at ``url`` holds, as a `Job` (none of it when the job committed nothing)."""
    from storage import open_dataset

    try:
        dataset = open_dataset(str(url))
    except Exception as exc:  # a job stopped before its first commit leaves no dataset to open
        print(f"{label}: no dataset at {url} ({exc})", file=sys.stderr)
        return Job(label, wall, stopped, 0, 0)
    records = dataset.task_records()
    steps: dict[str, float] = {}
    total = 0.0
    for record in records:
        if record.timings is None:
            continue
        total += record.timings.total.cpu
        for name, seconds in record.timings.steps.items():
            steps[name] = steps.get(name, 0.0) + seconds.cpu
    return Job(label, wall, stopped, len(records), len(dataset), steps, total)


def agreement(device_url: Path, cpu_url: Path) -> Agreement:
    """The samples of both datasets matched by id: how many agree in label, view state and point count."""
    from storage import open_dataset

    def columns(url: Path) -> dict[str, tuple[int, int, int]]:
        dataset = open_dataset(str(url))
        ids = dataset.column("sample_id").to_pylist()
        values = zip(
            dataset.values("label").tolist(),
            dataset.values("view_state").tolist(),
            dataset.values("num_points").tolist(),
            strict=True,
        )
        return dict(zip(ids, values, strict=True))

    device, cpu = columns(device_url), columns(cpu_url)
    common = sorted(set(device) & set(cpu))
    pairs = np.asarray([(*device[s], *cpu[s]) for s in common], dtype=np.int64).reshape(-1, 6)
    return Agreement(
        common=len(common),
        only_device=len(set(device) - set(cpu)),
        only_cpu=len(set(cpu) - set(device)),
        same_label=int(np.count_nonzero(pairs[:, 0] == pairs[:, 3])),
        same_view_state=int(np.count_nonzero(pairs[:, 1] == pairs[:, 4])),
        same_points=int(np.count_nonzero(pairs[:, 2] == pairs[:, 5])),
    )


def minutes(seconds: float) -> str:
    return f"{int(seconds // 60)} min {seconds % 60:04.1f} s"


def report(jobs: Sequence[Job], found: Agreement | None, setup: dict[str, str]) -> list[str]:
    lines = ["# The recipe's training set on a GPU and on the CPU (`benchmarks/generation/gpu_recipe.py`)", ""]
    lines += [f"- {name}: {value}" for name, value in setup.items()]
    header = "| job | wall | stopped at the budget | tasks | samples | task CPU-s | refinement CPU-s | host CPU-s |"
    lines += ["", header]
    lines += ["|---|---:|---|---:|---:|---:|---:|---:|"]
    for job in jobs:
        refine = job.step_cpu.get("refine_views", 0.0) + job.step_cpu.get("refine_cases", 0.0)
        host = job.step_cpu.get("refiner_host", 0.0)  # a shared host's part (its CPU, not the task's)
        cells = [job.label, minutes(job.wall), "yes" if job.stopped else "no", f"{job.tasks:,}", f"{job.samples:,}"]
        lines.append("| " + " | ".join([*cells, f"{job.task_cpu:,.0f}", f"{refine:,.0f}", f"{host:,.0f}"]) + " |")
    if len(jobs) == 2 and jobs[1].wall > 0:
        lines += ["", f"CPU job wall / device job wall: {jobs[1].wall / max(jobs[0].wall, 1e-9):.2f}x"]
    if found is not None:
        lines += ["", "| samples in both | same label | same view state | same point count | device only | CPU only |"]
        lines += ["|---:|---:|---:|---:|---:|---:|"]
        lines.append(
            f"| {found.common:,} | {found.same_label:,} | {found.same_view_state:,} | {found.same_points:,} | "
            f"{found.only_device:,} | {found.only_cpu:,} |"
        )
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--work", type=Path, required=True, help="a new or empty folder for the jobs")
    parser.add_argument("--device", default="cuda", help="cuda (the GPU job) or cpu (both on the CPU: a self-check)")
    parser.add_argument("--objects", type=Path, help="objects file (default: the first recipe's 40 objects)")
    parser.add_argument("--objects-count", type=int, help="keep only the first N objects (time is short)")
    parser.add_argument("--config", type=Path, help="generation config (default: the default config)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="workers per job (all cores)")
    parser.add_argument("--budget", type=float, help="seconds after which a job is stopped")
    parser.add_argument("--shared-refiner", action="store_true", help="the device job's network on one shared host")
    parser.add_argument("--refiner-batch", type=int, default=1, help="the shared host's jobs per encoder call")
    parser.add_argument("--out", type=Path, help="write the report here (a new file)")
    parser.add_argument("--replace", action="store_true", help="let --out replace an existing file")
    args = parser.parse_args(argv)
    if args.out is not None and args.out.exists() and not args.replace:
        parser.error(f"{args.out} exists; give another --out or --replace to write over it")
    if args.work.exists() and any(args.work.iterdir()):
        parser.error(f"--work {args.work} is not empty; give a new folder")
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            print("gpu_recipe: torch sees no CUDA device here; run it where one is, or --device cpu", file=sys.stderr)
            return 2
    args.work.mkdir(parents=True, exist_ok=True)
    objects = args.objects or recipe_objects(args.work)
    lines = [line for line in objects.read_text().splitlines() if line.strip() and not line.startswith("#")]
    if args.objects_count is not None:
        lines = lines[: args.objects_count]
    chosen = args.work / "objects.txt"
    chosen.write_text("\n".join(lines) + "\n")
    gpus = 1.0 / args.workers if args.device == "cuda" else 0.0
    jobs = []
    for label, share in (("device", gpus), ("cpu", 0.0)):
        shared = args.shared_refiner and label == "device"
        batch = args.refiner_batch
        command = submit_command(chosen, args.work / label, args.config, args.workers, share, shared, batch)
        wall, stopped = run_job(label, command, args.work, args.budget)
        jobs.append(dataset_job(label, args.work / label, wall, stopped))
        print(f"{label}: {minutes(wall)}{' (stopped)' if stopped else ''}", file=sys.stderr, flush=True)
    found = agreement(args.work / "device", args.work / "cpu") if all(job.samples for job in jobs) else None
    setup = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.node()}: {os.cpu_count()} CPUs, device {args.device}",
        "objects": f"{len(lines)} lines of {objects}" + (" (a subset: time was short)" if args.objects_count else ""),
        "config": str(args.config or "the default config"),
        "jobs": f"{args.workers} workers each; the device job's refiner on {args.device} "
        + (
            f"(one shared host, {args.refiner_batch} jobs per encoder call)"
            if args.shared_refiner
            else f"({gpus:g} GPU a task)"
        ),
        "budget": f"{args.budget:g} s a job" if args.budget else "none",
    }
    text = "\n".join(report(jobs, found, setup))
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
