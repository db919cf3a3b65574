"""Benchmark: does the one-shot planner fit its data? Nearest-cover F1 on the samples it trained on and
on held-out objects, against training steps and training-set size.

    python -m studies.planners.fit_curve --data WORK/train-data \\
        --run steps=WORK/osvp-recipe --run objects-10=WORK/curve/objects-10 ... \\
        --out studies/planners/results/fit-curve.md --png studies/planners/results/fit-curve.png

For every ``--run NAME=FOLDER`` (an `osvp train` output folder trained on ``--data``): its
``metrics.csv`` gives the held-out figures after every epoch (steps = epoch x batches per epoch), and
`osvp eval --split train` and ``--split val`` on its ``last.pt`` give the nearest-cover F1 (the
``size`` decoding, the figure ``best.pt`` is chosen by) on the training samples and the held-out
objects' samples at the end. The gap says what bounds the planner: a training F1 near the held-out
one means the network does not fit (capacity or optimisation), a large gap means it memorises.
Each evaluation is cached as ``FOLDER/eval-<split>-last.json``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.common import add_report_options, check_report
from studies.planners.runs import run, write_markdown

DECODING = "size"


def evaluate(folder: Path, data: str, split: str, threads: int) -> dict[str, Any]:
    """`osvp eval --split SPLIT --decoding size --json` of the run's last checkpoint, cached."""
    cache = folder / f"eval-{split}-last.json"
    if cache.exists():
        return dict(json.loads(cache.read_text()))
    command = ["osvp", "eval", "--data", data, "--checkpoint", str(folder / "last.pt"), "--split", split]
    command += ["--decoding", DECODING, "--json", "--threads", str(threads)]
    found = json.loads(run(command, folder / f"eval-{split}.log"))
    cache.write_text(json.dumps(found, indent=1))
    return dict(found)


def epochs(folder: Path) -> list[dict[str, float]]:
    """The run's metrics.csv rows as numbers (empty cells left out)."""
    with (folder / "metrics.csv").open() as handle:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(handle)]


def steps_per_epoch(history: list[dict[str, float]], batch_size: int) -> float:
    """Gradient steps of one epoch, from the logged throughput (samples/s x seconds = training samples)."""
    first = history[0]
    return math.ceil(first["train_samples_per_s"] * first["seconds"] / batch_size - 1e-6)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--data", required=True, help="the dataset every run was trained on")
    parser.add_argument("--run", action="append", required=True, help="NAME=FOLDER of an osvp train run")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--threads", type=int, default=2)
    add_report_options(parser)
    parser.add_argument("--png", type=Path)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    runs = [(name, Path(folder)) for name, folder in (pair.split("=", 1) for pair in args.run)]
    head = "| run | training samples | steps | held-out F1, best epoch | held-out F1, last | training F1, last | gap |"
    lines = [head, "|---|---|---|---|---|---|---|"]
    curves = {}
    for name, folder in runs:
        history = epochs(folder)
        per_epoch = steps_per_epoch(history, args.batch_size)
        train = evaluate(folder, args.data, "train", args.threads)
        held = evaluate(folder, args.data, "val", args.threads)
        fit, out = train["decodings"][DECODING]["cover_f1"], held["decodings"][DECODING]["cover_f1"]
        best = max(row["size_cover_f1"] for row in history)
        steps = int(per_epoch * len(history))
        lines.append(
            f"| {name} | {train['samples']:,} | {steps:,} | {best:.3f} | {out:.3f} | {fit:.3f} | {fit - out:+.3f} |"
        )
        curves[name] = ([per_epoch * row["epoch"] for row in history], [row["size_cover_f1"] for row in history], fit)
    print("\n".join(lines))
    if args.png:
        _draw(curves, args.png)
    if args.out:
        picture = ["", f"![fit curve]({args.png.name})"] if args.png else []
        write_markdown(args.out, "studies.planners.fit_curve", argv, [*lines, *picture])
    return 0


def _draw(curves: dict[str, tuple[list[float], list[float], float]], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8.0, 5.0), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.subplots()
    for name, (steps, held, fit) in curves.items():
        line = axes.plot(steps, held, marker=".", label=f"{name}: held-out objects")[0]
        axes.plot([steps[-1]], [fit], marker="*", markersize=12, color=line.get_color(), label=f"{name}: training")
    axes.set_xlabel("gradient steps (batch 32)")
    axes.set_ylabel("nearest-cover F1 (size decoding)")
    axes.set_title("osvp small, mincover: held out after every epoch, training samples at the end")
    axes.grid(alpha=0.3)
    axes.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(path)


if __name__ == "__main__":
    sys.exit(main())
