"""The dataset side at 1k, 10k and 100k tasks: files, opening, both readers and every `shards` command.

    python -m benchmarks.scale.dataset_commands --source before=/tmp/base-storage --source after=. \\
        [--sizes 1000 10000 100000] [--before-sizes 1000 10000] [--work /work/runs/scale] \\
        --out benchmarks/scale/results/dataset-commands.md --plot benchmarks/scale/results/dataset-commands.png

Per source tree and size N, the dataset is made by `benchmarks.scale.datasets` (a real job's tasks
written again under new ids through that tree's own writer and commit path, then finalised: the
tree's own layout), then every row runs in a fresh process measured by the kernel
(`benchmarks.scale.measure.run_measured`: CPU seconds, peak resident set) with the operation's own
seconds reported by the process (`benchmarks/scale/probe.py`, imports apart):

- the files a dataset holds (per task and per 1,000 samples), as written and packed (``shards pack``);
- `storage.open_dataset`, reading one sample, and the map-style and the streaming reader's first
  batch (2 workers, 32 samples of 2,048 points);
- ``datagen shards ls``, ``stats``, ``show``, ``validate`` (its default: every shard, coverage on a
  sample of rows), ``validate --sample 0.01``, ``repair`` (a sound dataset: it validates and stops),
  ``relabel`` and ``export`` (both with a deadline: they compute per sample) and ``evaluate
  --fixed-from`` (one built-in object, so the dataset's reading dominates).

The older tree's 100k dataset is not made (four million files); its rows stop at ``--before-sizes``.
Every figure is cached in ``WORK/storage-measurements.json`` (``--fresh`` measures again).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT, add_report_options, check_report
from benchmarks.scale.measure import Cache, Measurement, growth, machine_line, run_measured
from benchmarks.scale.objects import source_env

SIZES = (1_000, 10_000, 100_000)
HERE = Path(__file__).parent
PROBE = HERE / "probe.py"
DATASETS = HERE / "datasets.py"
DEADLINE = 600.0
"""Seconds a row may run before it is stopped (and reported as stopped, with its partial figure)."""

ROWS: tuple[tuple[str, str], ...] = (
    ("floor", "start-up of a reader process (imports), nothing read"),
    ("open", "`storage.open_dataset`"),
    ("sample", "open, then read one sample"),
    ("map-style", "map-style reader (`OSVPDataset`): first batch"),
    ("streaming", "streaming reader (`ShardStream`): first batch"),
    ("ls", "`shards ls`"),
    ("stats", "`shards stats`"),
    ("show", "`shards show URL 0`"),
    ("validate", "`shards validate`"),
    ("validate-sample", "`shards validate --sample 0.01`"),
    ("repair", "`shards repair` (a sound dataset)"),
    ("pack", "`shards pack` (512 MiB packs)"),
    ("open-packed", "`storage.open_dataset` of the packed dataset"),
    ("streaming-packed", "streaming reader of the packed dataset: first batch"),
    ("validate-packed", "`shards validate` of the packed dataset"),
    ("evaluate", "`evaluate --fixed-from` (one built-in object)"),
    ("relabel", "`shards relabel --alpha 9`"),
    ("export", "`shards export --layout air`"),
)
PROBED = {"floor", "open", "sample", "map-style", "streaming", "open-packed", "streaming-packed"}


def datagen(*args: str) -> list[str]:
    return [sys.executable, "-m", "datagen.cli.main", *args]


def command_of(row: str, url: Path, scratch: Path, report: Path) -> list[str] | None:
    """The command of one row on the dataset at ``url`` (None: not for this row)."""
    packed = url.with_name(f"{url.name}-packed")
    probe = {"open-packed": "open", "streaming-packed": "streaming"}.get(row, row)
    if row in PROBED:
        target = packed if row.endswith("-packed") else url
        return [sys.executable, str(PROBE), probe, str(target), str(report)]
    commands: dict[str, list[str]] = {
        "ls": datagen("shards", "ls", str(url)),
        "stats": datagen("shards", "stats", str(url)),
        "show": datagen("shards", "show", str(url), "0"),
        "validate": datagen("shards", "validate", str(url)),
        "validate-sample": datagen("shards", "validate", str(url), "--sample", "0.01"),
        "validate-packed": datagen("shards", "validate", str(packed)),
        "repair": datagen("shards", "repair", str(url), "--home", str(scratch / "home")),
        "pack": datagen("shards", "pack", str(url), "--out", str(packed)),
        "relabel": datagen("shards", "relabel", str(url), "--out", str(scratch / "relabel"), "--alpha", "9"),
        "export": datagen("shards", "export", str(url), str(scratch / "export"), "--layout", "air", "--points", "512"),
        "evaluate": datagen(
            "evaluate",
            "--objects",
            str(scratch / "one.txt"),
            "--planner",
            "fixed",
            "--fixed-from",
            str(url),
            "--rotations",
            "0",
        ),
    }
    return commands.get(row)


def make_dataset(label: str, source: Path, size: int, work: Path, env: dict[str, str]) -> Path:
    """The tree's dataset of ``size`` tasks (made once: its source job, then the replicas)."""
    origin = work / label / "source"
    url = work / label / f"tasks-{size}"
    (work / label).mkdir(parents=True, exist_ok=True)
    if not (origin / "dataset.json").exists():
        run_measured(
            [sys.executable, str(DATASETS), "source", "--out", str(origin)],
            cwd=source,
            env=env,
            stdout=work / label / "source.log",
        )
    manifest, legacy = url / "index" / "manifest.json", url / "index.json"
    if not (manifest.exists() or legacy.exists()):
        replicate = ["replicate", "--source", str(origin), "--out", str(url), "--tasks", str(size)]
        made = run_measured(
            [sys.executable, str(DATASETS), *replicate],
            cwd=source,
            env=env,
            stdout=work / label / f"make-{size}.log",
        )
        if made.rc != 0:
            raise SystemExit(f"making {url} failed: see {work / label / f'make-{size}.log'}")
    return url


def file_counts(url: Path) -> dict[str, float]:
    files = sum(len(names) for _, _, names in os.walk(url))
    size = sum((Path(top) / name).stat().st_size for top, _, names in os.walk(url) for name in names)
    return {"files": files, "bytes": size}


def measure(
    labels: dict[str, Path], sizes: dict[str, Sequence[int]], work: Path, cache: Cache, rows: Sequence[str]
) -> None:
    for label, source in labels.items():
        env = source_env(source, os.environ)
        for size in sizes[label]:
            url = make_dataset(label, source, size, work, env)
            key = f"{label}/{size}"
            if cache.get(f"{key}/files") is None:
                cache.put(f"{key}/files", file_counts(url))
            scratch = work / label / f"scratch-{size}"
            for row in rows:
                if cache.get(f"{key}/{row}") is not None:
                    continue
                shutil.rmtree(scratch, ignore_errors=True)
                scratch.mkdir(parents=True)
                (scratch / "one.txt").write_text("builtin:capsule\n")
                report = scratch / "report.json"
                command = command_of(row, url, scratch, report)
                if command is None:
                    continue
                if row.endswith("-packed") and not url.with_name(f"{url.name}-packed").exists():
                    continue
                print(f"{key}: {row}", file=sys.stderr, flush=True)
                found = run_measured(
                    command,
                    cwd=source,
                    env=env,
                    stdout=work / label / f"{row}-{size}.log",
                    deadline=DEADLINE,
                    report=report if row in PROBED else None,
                )
                cache.put(f"{key}/{row}", found.to_json())
                if row == "pack" and found.rc == 0:
                    cache.put(f"{key}/files-packed", file_counts(url.with_name(f"{url.name}-packed")))


def _cell(found: dict[str, Any] | None) -> str:
    if found is None:
        return ""
    m = Measurement.from_json(found)
    own = m.extra.get("seconds")
    seconds = f"{own:.2f} s ({m.wall:.1f} s)" if own is not None else f"{m.wall:.1f} s"
    stop = " stopped" if m.stopped else "" if m.rc == 0 else f" rc {m.rc}"
    return f"{seconds}, {m.cpu:.1f} CPU-s, {m.peak_mb:.0f} MB{stop}"


def report(labels: Sequence[str], sizes: dict[str, Sequence[int]], cache: Cache) -> str:
    every = sorted({n for label in labels for n in sizes[label]})
    lines = [
        "# Scale: the dataset side at 1k, 10k and 100k tasks",
        "",
        f"Made by `python -m benchmarks.scale.dataset_commands` on {datetime.date.today().isoformat()}:",
        f"{machine_line()}.",
        "Each cell: the operation's own seconds where the process reports them (the whole process's wall",
        "seconds in brackets), its CPU seconds and peak resident memory; `stopped`: it passed the",
        f"{DEADLINE:.0f} s deadline. Growth: the ratio of each size to the one before and a log-log slope",
        "(1 is linear in the tasks, 0 flat) of the operation's seconds.",
        "",
    ]
    for label in labels:
        lines += [f"## {label}", ""]
        header = ["row", *[f"{n:,} tasks" for n in every], "growth"]
        lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        files = []
        for n in every:
            found = cache.get(f"{label}/{n}/files")
            packed = cache.get(f"{label}/{n}/files-packed")
            cell = "" if found is None else f"{found['files']:,} files, {found['bytes'] / 1e9:.2f} GB"
            if packed is not None:
                cell += f"; packed {packed['files']:,}"
            files.append(cell)
        lines.append("| files on disk (as written; packed) | " + " | ".join(files) + " | |")
        for row, title in ROWS:
            cells = [_cell(cache.get(f"{label}/{n}/{row}")) for n in every]
            if not any(cells):
                continue
            seconds = {
                n: float(found["extra"].get("seconds", found["wall"]))
                for n in every
                if (found := cache.get(f"{label}/{n}/{row}")) is not None and not found["stopped"]
            }
            lines.append(f"| {title} | " + " | ".join(cells) + f" | {growth(seconds)} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", action="append", default=[], help="LABEL=TREE (default after=.)")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--before-sizes", type=int, nargs="+", default=[1_000, 10_000])
    parser.add_argument("--rows", nargs="+", default=[row for row, _ in ROWS])
    parser.add_argument("--work", type=Path, default=Path("/tmp/datagen-scale-storage"))
    parser.add_argument("--fresh", action="store_true")
    add_report_options(parser)
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()
    check_report(parser, args.out, args.replace)
    labels = dict(item.split("=", 1) for item in args.source) if args.source else {"after": "."}
    trees = {label: Path(tree).resolve() for label, tree in labels.items()}
    sizes = {label: args.before_sizes if label == "before" else args.sizes for label in trees}
    args.work.mkdir(parents=True, exist_ok=True)
    path = args.work / "storage-measurements.json"
    if args.fresh and path.exists():
        path.unlink()
    cache = Cache(path)
    measure(trees, sizes, args.work, cache, args.rows)
    text = report(list(trees), sizes, cache)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    if args.plot:
        plot(list(trees), sizes, cache, args.plot)


def plot(labels: Sequence[str], sizes: dict[str, Sequence[int]], cache: Cache, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(12, 5))
    for label in labels:
        for row, _ in ROWS:
            points = [(n, found) for n in sizes[label] if (found := cache.get(f"{label}/{n}/{row}")) is not None]
            if len(points) < 2:
                continue
            xs = [n for n, _ in points]
            left.plot(xs, [f["extra"].get("seconds", f["wall"]) for _, f in points], marker="o", label=f"{label} {row}")
            right.plot(xs, [f["peak_mb"] for _, f in points], marker="o", label=f"{label} {row}")
    for axis, name in ((left, "seconds"), (right, "peak MB")):
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xlabel("tasks")
        axis.set_ylabel(name)
        axis.grid(True, which="both", alpha=0.3)
    left.legend(fontsize=6, ncol=2)
    figure.tight_layout()
    figure.savefig(out, dpi=120)


if __name__ == "__main__":
    sys.path.insert(0, str(REPO_ROOT))
    main()
