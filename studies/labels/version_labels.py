"""Benchmark: are a new refiner version's labels as good as the old one's? Judged by `datagen evaluate`.

    python -m studies.labels.version_labels  # poco_version 1 against 2, seeds 0 and 1
    python -m studies.labels.version_labels --versions 1 2 --seeds 0 1 2 --workers 2
    python -m studies.labels.version_labels --versions 2 --variants "band6=band = 0.006" --seeds 0 1

For each (version, seed) the dataset's own labels (`--planner oracle`) are played on the unseen
watertight shared meshes (examples/watertight-meshes.txt), rotations 0 and 4 of 8, initial views 0, 8,
16 and 24: 48 runs per config, each the pipeline of a whole task on that object. Printed: coverage,
views and movement per config, then every pair of configs compared run by run (the mean change of
coverage, its mean size, and how many runs chose another view set).

The spread to be within is the seed's: two seeds of one version refine with other input subsets and
draw other cases, so their labels differ as much as two equally good datasets can. A new version
whose labels differ from the old one's, at the same seed, by no more than that is as good by this
measure (issue 24's rule for a refiner version that changes outputs). ``--variants NAME=SETTINGS``
judges a candidate that is not a version yet the same way: the first version's config plus the given
settings (TOML lines, ``;`` between them; a ``poco_version`` among them replaces the first version),
e.g. a narrower band.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from benchmarks.common import REPO_ROOT

OBJECTS = REPO_ROOT / "examples" / "watertight-meshes.txt"


@dataclass(frozen=True)
class Run:
    coverage: float
    """Percent of the reference surface."""
    views: tuple[int, ...]
    metres: float


Runs = dict[tuple[str, int, int], Run]


def evaluate(settings: str, seed: int, folder: Path, workers: int, name: str) -> Runs:
    """The oracle's runs for one (config settings, seed), keyed by (object, rotation, initial view)."""
    config = folder / f"{name}-seed{seed}.toml"
    config.write_text(f"rotations = 8\n{settings}\nseed = {seed}\n")
    command = [
        "datagen", "evaluate", "--objects", str(OBJECTS), "--config", str(config), "--planner", "oracle",
        "--rotations", "0,4", "--initial-views", "0,8,16,24", "--workers", str(workers), "--json",
    ]  # fmt: skip
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run(command, cwd=REPO_ROOT, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"datagen evaluate failed ({done.returncode}): {done.stderr[-2000:]}")
    return runs_of(json.loads(done.stdout))


def runs_of(report: dict[str, object]) -> Runs:
    runs: Runs = {}
    for run in report["runs"]:  # type: ignore[attr-defined]
        if run["planner"] != "oracle":
            continue
        key = (run["object_name"], int(run["rotation"]), int(run["initial_view"]))
        coverage = 100.0 * run["observed_size"] / run["reference_size"] if run["reference_size"] else 0.0
        runs[key] = Run(coverage, tuple(sorted(run["visited"])), float(sum(run["step_metres"])))
    return runs


def report(results: dict[str, Runs]) -> list[str]:
    lines = ["| config | runs | coverage % | views | movement m |", "|---|---:|---:|---:|---:|"]
    for label, runs in results.items():
        coverage = [r.coverage for r in runs.values()]
        views = [len(r.views) for r in runs.values()]
        lines.append(
            f"| {label} | {len(runs)} | {statistics.mean(coverage):.2f} | {statistics.mean(views):.2f} | "
            f"{statistics.mean(r.metres for r in runs.values()):.2f} |"
        )
    lines += [
        "",
        "| second - first | runs | coverage change | mean size of the change | view count change | other view set |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for (first, a), (second, b) in itertools.combinations(results.items(), 2):
        keys = sorted(set(a) & set(b))
        if not keys:
            continue
        change = [b[k].coverage - a[k].coverage for k in keys]
        views = [len(b[k].views) - len(a[k].views) for k in keys]
        other = sum(a[k].views != b[k].views for k in keys)
        lines.append(
            f"| {second} - {first} | {len(keys)} | {statistics.mean(change):+.2f} | "
            f"{statistics.mean(abs(c) for c in change):.2f} | {statistics.mean(views):+.2f} | {other} |"
        )
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--versions", nargs="+", type=int, default=[1, 2], help="poco_version values (default 1 2)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1], help="seeds (default 0 1)")
    parser.add_argument("--workers", type=int, default=1, help="objects evaluated side by side (default 1)")
    parser.add_argument(
        "--variants",
        nargs="*",
        default=[],
        help="NAME=SETTINGS: the first version's config plus these TOML lines (';' between them)",
    )
    args = parser.parse_args(argv)
    candidates = {f"version {v}": (f"v{v}", f"poco_version = {v}") for v in args.versions}
    for variant in args.variants:
        name, _, settings = variant.partition("=")
        if not name or not settings:
            parser.error(f"--variants {variant!r}: give NAME=SETTINGS")
        lines = settings.replace(";", "\n")
        version = "" if "poco_version" in lines else f"poco_version = {args.versions[0]}\n"
        candidates[name] = (name, version + lines)
    results: dict[str, Runs] = {}
    with tempfile.TemporaryDirectory() as folder:
        for seed, (label, (name, settings)) in itertools.product(args.seeds, candidates.items()):
            labelled = f"{label}, seed {seed}"
            results[labelled] = evaluate(settings, seed, Path(folder), args.workers, name)
            print(f"{labelled}: {len(results[labelled])} runs", flush=True)
    print("\n".join(report(results)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
