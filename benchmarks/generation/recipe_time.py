"""Benchmark: how long a real training set takes, as a user makes it (`datagen submit`, local Ray).

    python -m benchmarks.generation.recipe_time --work /tmp/recipe-time            # default config
    python -m benchmarks.generation.recipe_time --work W --configs v1.toml v2.toml  # one job each, in turn

The objects are the first osvp recipe's 40 (issue 16): the 22 built-ins, 11 seeded synthetic shapes
(`datagen objects synth --count 11 --seed 7`) and 7 shared meshes; each config's ``rotations`` sets the
tasks (the recipe's 8: 320 tasks). Each config runs as one fresh `datagen submit` (its own ledger and
dataset folder under ``--work``, Ray started by the command, all cores), timed from launch to exit;
then `datagen shards stats --json` gives the samples and every step's CPU seconds. Printed: wall
time, tasks, samples, task CPU per step, and each config's wall time against the first's, with the
cores the machine kept busy while each ran (above the job's own means other load). ``--objects``
takes another objects file.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import REPO_ROOT, SHARED_MESHES

RECIPE_MESHES = (
    "stanford-bunny.obj name=bunny up=y",
    "teapot.obj up=y",
    "alligator.obj",
    "beast.obj",
    "beetle.obj",
    "ogre.obj",
    "suzanne.obj",
)
"""The shared meshes of the first recipe (none of them among the unseen evaluation meshes)."""
SYNTHETIC = 11


@dataclass(frozen=True)
class JobTime:
    label: str
    wall: float
    tasks: int
    samples: int
    step_seconds: dict[str, float]
    busy: float
    """Cores the whole machine kept busy on average while it ran (this job included)."""


def recipe_objects(work: Path) -> Path:
    """The 40-object file (written under ``work``); shared meshes missing here are left out, said so."""
    synth = work / "synth"
    run(["datagen", "objects", "synth", "--count", str(SYNTHETIC), "--seed", "7", "--out", str(synth)])
    builtin_lines = (REPO_ROOT / "examples" / "builtin.txt").read_text().splitlines()
    builtins = [line for line in builtin_lines if line.startswith("builtin:")]
    synth_lines = (synth / "objects.txt").read_text().splitlines()
    synthetic = [f"{synth / line}" for line in synth_lines if line.strip() and not line.startswith("#")]
    meshes = []
    for line in RECIPE_MESHES:
        path = SHARED_MESHES / line.split()[0]
        if path.is_file():
            meshes.append(f"{SHARED_MESHES}/{line}")
        else:
            print(f"note: {path} not found; the job runs without it", file=sys.stderr)
    objects = work / "recipe-objects.txt"
    objects.write_text("\n".join(["# the first osvp recipe's objects", *builtins, *synthetic, *meshes]) + "\n")
    return objects


def run(command: Sequence[str], env: dict[str, str] | None = None) -> str:
    done = subprocess.run(command, cwd=REPO_ROOT, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return done.stdout


def busy_seconds() -> float:
    """Busy CPU seconds of the whole machine since boot (/proc/stat)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def time_job(label: str, objects: Path, config: Path | None, work: Path) -> JobTime:
    """One fresh `datagen submit` of ``objects`` under ``config``, timed, then its stats."""
    out = work / f"data-{label}"
    env = {**os.environ, "DATAGEN_HOME": str(work / f"home-{label}"), "OPENBLAS_NUM_THREADS": "1"}
    env.pop("RAY_ADDRESS", None)
    command = ["datagen", "submit", "--objects", str(objects), "--out", str(out)]
    if config is not None:
        command += ["--config", str(config)]
    busy, start = busy_seconds(), time.perf_counter()
    run(command, env)
    wall = time.perf_counter() - start
    machine = (busy_seconds() - busy) / wall  # Ray's processes are not our children: count the machine
    stats = json.loads(run(["datagen", "shards", "stats", str(out), "--json"], env))
    timed = stats.get("step_seconds") or {"steps": {}}
    steps = {name: float(value["cpu"]) for name, value in timed["steps"].items()}
    return JobTime(label, wall, int(stats["committed_tasks"]), int(stats["samples"]), steps, machine)


def minutes(seconds: float) -> str:
    return f"{int(seconds // 60)} min {seconds % 60:04.1f} s"


def report(jobs: Sequence[JobTime]) -> list[str]:
    first = jobs[0]
    lines = [
        "| config | tasks | samples | wall | first / this | task CPU-s | CPU-s per task | machine busy (cores) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for job in jobs:
        cpu = sum(job.step_seconds.values())
        lines.append(
            f"| {job.label} | {job.tasks} | {job.samples:,} | {minutes(job.wall)} | {first.wall / job.wall:.2f}x | "
            f"{cpu:,.0f} | {cpu / max(1, job.tasks):.2f} | {job.busy:.2f} of {os.cpu_count()} |"
        )
    steps = list(dict.fromkeys(name for job in jobs for name in job.step_seconds))
    lines += ["", "| step | " + " | ".join(f"{job.label} CPU-s" for job in jobs) + " |", "|---|" + "---:|" * len(jobs)]
    for step in steps:
        lines.append(f"| {step} | " + " | ".join(f"{job.step_seconds.get(step, 0.0):,.1f}" for job in jobs) + " |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--work", type=Path, required=True, help="scratch folder for the ledgers and datasets")
    parser.add_argument("--configs", nargs="*", type=Path, help="generation configs (default: the recipe's)")
    parser.add_argument("--objects", type=Path, help="objects file (default: the first recipe's 40 objects)")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    objects = args.objects or recipe_objects(args.work)
    configs: list[Path | None] = list(args.configs) if args.configs else [REPO_ROOT / "osvp/recipe/training.toml"]
    jobs = []
    for config in configs:
        label = config.stem if config is not None else "default"
        job = time_job(label, objects, config, args.work)
        print(f"{label}: {job.tasks} tasks, {job.samples:,} samples in {minutes(job.wall)}", flush=True)
        jobs.append(job)
    print("\n".join(report(jobs)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
