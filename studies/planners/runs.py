"""Shared steps of the planner benchmarks (`target_ablation.py`, `learning_curve.py`, `label_margin.py`):
train an osvp planner, measure it on held-out samples, and play it on unseen meshes beside random views
and the best fixed view set of its training data at equal view counts. Every step is a subprocess of
the installed commands (`osvp`, `datagen`), exactly what a user runs, and each result is cached in the
output folder, so an interrupted benchmark resumes.

Training budget: every run takes the same number of gradient steps (`osvp train --steps`), whatever
its training set's size, so a point of a learning curve differs from another only by its data.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
WATERTIGHT = REPO_ROOT / "examples" / "watertight-meshes.txt"
"""The six unseen test meshes (none of them in the recipe's training objects)."""


@dataclass(frozen=True)
class TrainSpec:
    """One `osvp train` run."""

    name: str
    target: str = "label"
    network: str = "osvp"
    lambda_: float = 2.0
    max_objects: int | None = None
    sample_fraction: float | None = None
    val_fraction: float = 0.07
    """Of the objects: 6 of 86 held out for validation leaves 80 to train on."""
    seed: int = 0

    def arguments(self, data: str, out: Path, steps: int, threads: int) -> list[str]:
        found = ["--data", data, "--out", str(out), "--network", self.network, "--preset", "small"]
        found += ["--target", self.target]
        found += ["--lambda", f"{self.lambda_:g}", "--steps", str(steps), "--split", "objects"]
        found += ["--val-fraction", f"{self.val_fraction:g}", "--seed", str(self.seed), "--threads", str(threads)]
        if self.max_objects is not None:
            found += ["--max-objects", str(self.max_objects)]
        if self.sample_fraction is not None:
            found += ["--sample-fraction", f"{self.sample_fraction:g}"]
        return found


def run(command: Sequence[str], log: Path) -> str:
    """Run a command, its stderr to ``log``; stdout back. A failure stops the benchmark with the log's end."""
    with log.open("a") as stream:
        done = subprocess.run(command, stdout=subprocess.PIPE, stderr=stream, text=True, env=ENV, check=False)
    if done.returncode:
        tail = log.read_text().splitlines()[-5:]
        sys.exit(f"{' '.join(command[:3])} failed (exit {done.returncode}); {log}:\n" + "\n".join(tail))
    return done.stdout


def train(spec: TrainSpec, data: str, out: Path, steps: int, threads: int) -> Path:
    """Train (or resume) ``spec`` into ``out/<name>``; the run's best checkpoint."""
    folder = out / spec.name
    best = folder / "best.pt"
    if (folder / "done").exists():
        return best
    folder.mkdir(parents=True, exist_ok=True)
    resume = ["--resume"] if (folder / "last.pt").exists() else []
    started = time.perf_counter()
    run(["osvp", "train", *spec.arguments(data, folder, steps, threads), *resume], folder / "train.log")
    (folder / "done").write_text(json.dumps({"seconds": time.perf_counter() - started}))
    return best


def held_out(checkpoint: Path, data: str, decodings: Sequence[str], threads: int) -> dict[str, Any]:
    """`osvp eval --split val --json`: the figures per decoding on the validation objects' samples."""
    cache = checkpoint.with_name("eval-val.json")
    if cache.exists():
        return dict(json.loads(cache.read_text()))
    command = ["osvp", "eval", "--data", data, "--checkpoint", str(checkpoint), "--split", "val", "--json"]
    command += ["--threads", str(threads)] + [part for d in decodings for part in ("--decoding", d)]
    found = json.loads(run(command, checkpoint.with_name("eval.log")))
    cache.write_text(json.dumps(found, indent=1))
    return dict(found)


def unseen(
    planners: Sequence[str],
    out: Path,
    name: str,
    objects: Path = WATERTIGHT,
    fixed_from: str | None = None,
    extra: Sequence[str] = (),
) -> dict[str, Any]:
    """`datagen evaluate --json` of ``planners`` on the unseen meshes (rotations 0 and 4, initial
    views 0, 8, 16, 24: 48 runs per planner), with the fixed plans of ``fixed_from`` (every planner's
    lift over the constant plan) and ``extra`` options, cached as ``out/<name>.json``."""
    cache = out / f"{name}.json"
    if cache.exists():
        return dict(json.loads(cache.read_text()))
    out.mkdir(parents=True, exist_ok=True)
    command = ["datagen", "evaluate", "--objects", str(objects), "--rotations", "0,4", "--initial-views", "0,8,16,24"]
    command += [*(["--fixed-from", fixed_from] if fixed_from else []), *extra]
    command += ["--json"] + [part for p in planners for part in ("--planner", p)]
    found = json.loads(run(command, out / f"{name}.log"))
    cache.write_text(json.dumps(found, indent=1))
    return dict(found)


def matched(planner: str) -> list[str]:
    """The planner, random views and the best fixed set at its view count, run by run (fixed needs the
    evaluation's ``fixed_from``)."""
    return [planner, f"random:match={planner}", f"fixed:match={planner}"]


def row_of(result: dict[str, Any], planner: str) -> dict[str, Any]:
    """The summary row of ``planner`` in a `datagen evaluate --json` result."""
    return next(r for r in result["rows"] if r["planner"] == planner)


def pm(row: dict[str, Any], key: str, decimals: int = 2) -> str:
    value, spread = row.get(key), row.get(f"{key}_std")
    if value is None:
        return "-"
    return f"{value:.{decimals}f} ± {spread:.{decimals}f}" if spread is not None else f"{value:.{decimals}f}"


def write_markdown(path: Path, module: str, argv: Sequence[str] | None, lines: Sequence[str]) -> None:
    """``lines`` as a Markdown file headed by the command that made it (``python -m MODULE ARGS``)."""
    command = f"python -m {module} " + " ".join(argv if argv is not None else sys.argv[1:])
    path.parent.mkdir(parents=True, exist_ok=True)  # an hour's judgement must not die on a missing folder
    path.write_text("\n".join([f"Made by `{command}`.", "", *lines, ""]))
