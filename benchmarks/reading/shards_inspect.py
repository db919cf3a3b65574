"""Benchmark: how long each ``datagen shards`` command takes on a ~10k-sample local dataset.

(Issue 7 calls it inspect.py; that name would shadow the standard library's ``inspect`` for a
script run from its own folder, so it is shards_inspect.py.)

    python -m benchmarks.reading.shards_inspect [--url DATASET] [--rotations 10] [--workers 2] [--keep DIR]

The dataset is built by the engine (`datagen.api.submit`, local Ray) from every built-in except the
two torus knots (their labels take 10-80 s a task to compute, which would dominate the build and
not the commands), refiner none, default config otherwise with ``rotations`` set to 10: 20 objects x
10 rotations = 200 tasks, 11,052 samples at the default alpha (built in about 4 minutes with 2
workers on a loaded 2-core machine). ``--url`` reuses a dataset instead (any size; the counts are
printed). ``--keep DIR`` builds into DIR and leaves it there for reuse.

Each command runs once in this process through typer's CliRunner, as a user would call it; wall
seconds are printed per command, with labels per second for ``validate --all`` and ``relabel``.
Targets: ``ls``, ``show``, ``stats`` and ``validate`` (without --all) each under 5 s. Commands not
registered yet (``ls``, ``show``, ``stats`` come from another module) are skipped with a message.

Measured on that dataset (2 cores shared with other work, so +-30%): ls 1.0-1.6 s, show 0.1 s,
stats 0.1 s, validate 21-29 s (storage.validate reads every array of every shard: 14-19 s; the
sampled label check 4.4 s), validate --all 24-33 s (the label check alone 5 s, 2,200 labels/s),
relabel to alpha 5 150-175 s (63-73 labels/s, 80% of it the pipeline's own tie-break search).
"""

from __future__ import annotations

from benchmarks.common import limit_threads

limit_threads()

import argparse  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

from typer.testing import CliRunner  # noqa: E402

from datagen.cli.main import app  # noqa: E402
from datagen.cli.shards import shards_app  # noqa: E402
from datagen.shapes.builtins import builtin_names  # noqa: E402
from storage import open_dataset  # noqa: E402

SKIPPED_BUILTINS = ("torus_knot", "torus_knot_3_5")
TARGET_SECONDS = 5.0
TARGETED = ("ls", "show", "stats", "validate")


@dataclass(frozen=True)
class Timing:
    command: str
    seconds: float
    exit_code: int
    labels: int = 0
    """Labels the command computed or checked (for labels per second)."""


def build(folder: Path, rotations: int, workers: int) -> str:
    """An engine-written dataset of the built-ins (see the module docstring); returns its URL."""
    from datagen import api
    from datagen.settings import RunSettings

    names = [name for name in builtin_names() if name not in SKIPPED_BUILTINS]
    objects = folder / "objects.txt"
    objects.write_text("".join(f"builtin:{name}\n" for name in names))
    config = folder / "config.toml"
    config.write_text(f'rotations = {rotations}\nrefiner = "none"\n')
    print(f"building {len(names)} built-ins x {rotations} rotations = {len(names) * rotations} tasks ...", flush=True)
    started = time.perf_counter()
    job = api.submit(
        objects,
        config,
        RunSettings(home=folder / "home", out=str(folder / "dataset"), num_workers=workers, ray_address=None),
    )
    print(f"built in {time.perf_counter() - started:.0f} s: {job.state}, {job.summary.get('samples')} samples")
    import ray

    ray.shutdown()  # its idle workers would otherwise share the CPUs with the timed commands
    return job.out


def run(runner: CliRunner, name: str, args: list[str], labels: int = 0) -> Timing:
    started = time.perf_counter()
    result = runner.invoke(app, ["shards", *args])
    seconds = time.perf_counter() - started
    if result.exit_code != 0:
        print(f"  {name} exited {result.exit_code}: {result.output.strip().splitlines()[-1:]}")
    return Timing(name, seconds, result.exit_code, labels)


def registered() -> set[str]:
    return {str(command.name) for command in shards_app.registered_commands}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="Reuse this dataset instead of building one.")
    parser.add_argument("--rotations", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--keep", type=Path, help="Build into this folder and keep it.")
    args = parser.parse_args()

    scratch = Path(tempfile.mkdtemp(prefix="inspect-bench-"))
    try:
        if args.url:
            url = args.url
        else:
            folder = args.keep or scratch / "build"
            folder.mkdir(parents=True, exist_ok=True)
            url = build(folder, args.rotations, args.workers)
        dataset = open_dataset(url)
        samples, tasks = len(dataset), len(set(dataset.index.column("task_id").to_pylist()))
        alpha = dataset.info.config.alpha
        print(f"dataset {url}: {samples} samples in {tasks} tasks, alpha {alpha}")
        first_sample = dataset.index.column("sample_id")[0].as_py()

        runner = CliRunner()
        available = registered()
        timings: list[Timing] = []
        new_alpha = str(max(1, alpha - 5))
        plan: list[tuple[str, list[str], int]] = [
            ("ls", ["ls", url], 0),
            ("show SAMPLE", ["show", url, first_sample], 0),
            ("stats", ["stats", url], 0),
            ("validate", ["validate", url], 0),
            ("validate --all", ["validate", url, "--all"], samples),
            (
                f"relabel --alpha {new_alpha}",
                ["relabel", url, "--alpha", new_alpha, "--out", str(scratch / "new")],
                samples,
            ),
        ]
        for name, command, labels in plan:
            if command[0] not in available:
                print(f"  {command[0]}: not registered in this checkout, skipped")
                continue
            print(f"  running {name} ...", flush=True)
            timings.append(run(runner, name, command, labels))

        print(f"\n{'command':<24} {'seconds':>8} {'labels/s':>10}  target")
        for timing in timings:
            rate = f"{timing.labels / timing.seconds:10.0f}" if timing.labels else " " * 10
            name = timing.command.split()[0]
            target = ""
            if name in TARGETED and "--all" not in timing.command:
                target = "ok (< 5 s)" if timing.seconds < TARGET_SECONDS else "MISSED (>= 5 s)"
            failed = "" if timing.exit_code == 0 else f" (exit {timing.exit_code})"
            print(f"{timing.command:<24} {timing.seconds:8.2f} {rate}  {target}{failed}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
