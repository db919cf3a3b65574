"""Benchmark: what more distinct objects teach a planner, judged against the ceiling over the data-free plans
(issue 43).

    python -m studies.planners.curve_ceiling --work NEW_DIR --config EVAL.toml \\
        --data nbvnet=DATASET --data one-shot=RELABELLED_DATASET [--objects 37,150,all] \\
        [--steps 2000] [--threads 1] [--parallel 2] [--val-fraction 0.03] [--workers 2] \\
        [--eval-objects examples/watertight-meshes.txt] [--out REPORT.md --replace]

For every family (``--data FAMILY=URL``, a planner family of `FAMILIES`) and every object count, one
`osvp train` on a seeded, nested draw of that many of the dataset's training objects, every run the
same number of gradient steps (``--steps``) and the same held-out objects, so a point differs from
another only by its data. Then one `datagen evaluate --margins 3,4,6` plays every trained planner on
the unseen meshes (rotations 0 and 4 of 8, initial views 0, 8, 16 and 24) beside the ceiling
(``gain``: the true gains played step by step) and the floor's two plans (``fixed``, chosen on the
first family's dataset, and ``spread``).

Reported per family and point: the captured share of the ceiling's margin over the floor at 3, 4
and 6 views (the ratio of mean margins over the objects), the margins themselves, the views to see
95 % of the surface; for a one-shot family also its coverage at its own view count against the better
of the fixed and spread plans at that count, run by run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from statistics import mean
from typing import Any

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure

from benchmarks.common import add_report_options, check_report
from studies.planners.runs import WATERTIGHT, TrainSpec, run, train, write_markdown

BUDGETS = (3, 4, 6)


@dataclass(frozen=True)
class Family:
    """A planner family: how it is trained and how `datagen evaluate` plays it."""

    network: str
    target: str
    planner: str
    """The evaluate planner prefix before ``:CHECKPOINT``."""
    one_shot: bool
    """Takes its views at once (judged at its own count too) rather than step by step."""


FAMILIES: dict[str, Family] = {
    "nbvnet": Family(network="nbvnet", target="best_view", planner="osvp", one_shot=False),
    "one-shot": Family(network="osvp", target="label", planner="osvp+tuned", one_shot=True),
}
"""NBVNet-style (the grid CNN, the best next view as a class, played step by step) and the one-shot
set planner trained on the stored label of its dataset (relabel it with the objective to learn)."""


@dataclass(frozen=True)
class Point:
    family: str
    data: str
    count: int | None
    """Training objects; None: every object of the training side."""

    @property
    def name(self) -> str:
        return f"{self.family}-{self.count if self.count is not None else 'all'}"


def points_of(datasets: dict[str, str], counts: Sequence[int | None]) -> list[Point]:
    return [Point(family, data, count) for family, data in datasets.items() for count in counts]


def train_point(point: Point, work: Path, steps: int, threads: int, val_fraction: float) -> Path:
    family = FAMILIES[point.family]
    spec = TrainSpec(
        point.name,
        target=family.target,
        network=family.network,
        max_objects=point.count,
        val_fraction=val_fraction,
    )
    return train(spec, point.data, work, steps, threads)


def planner_of(point: Point, checkpoint: Path) -> str:
    return f"{FAMILIES[point.family].planner}:{checkpoint}"


def evaluate(
    planners: Sequence[str],
    work: Path,
    config: Path,
    objects: Path,
    fixed_from: str,
    workers: int,
    name: str = "evaluate",
) -> dict[str, Any]:
    """One `datagen evaluate --json` of every planner beside the ceiling and the floor, cached as
    ``work/NAME.json``."""
    cache = work / f"{name}.json"
    if cache.exists():
        return dict(json.loads(cache.read_text()))
    command = ["datagen", "evaluate", "--objects", str(objects), "--config", str(config)]
    command += ["--rotations", "0,4", "--initial-views", "0,8,16,24", "--fixed-from", fixed_from]
    command += ["-p", "gain", "-p", "fixed", "-p", "spread", "--margins", ",".join(map(str, BUDGETS))]
    command += ["--workers", str(workers), "--json"] + [part for p in planners for part in ("-p", p)]
    found = json.loads(run(command, work / f"{name}.log"))
    cache.write_text(json.dumps(found) + "\n")
    return dict(found)


def trained_on(checkpoint: Path) -> dict[str, Any]:
    """Training objects and samples of a run, and its held-out figure (the metric its best epoch was
    chosen by, on the validation objects' samples), from its checkpoint's own record."""
    from osvp.checkpoint import load_checkpoint

    training = load_checkpoint(checkpoint).training
    metric, epoch = str(training.get("best_metric", "")), int(training.get("best_epoch", 0))
    history = training.get("history") or []
    value = float(history[epoch - 1].get(metric, math.nan)) if 0 < epoch <= len(history) else math.nan
    return {
        "objects": int(training.get("train_objects", 0)),
        "samples": int(training["train_samples"]),
        "epochs": len(history),
        "held_out": (metric, value),
    }


def same_planner(label: str, planner: str) -> bool:
    """Whether a margin row's planner label is ``planner`` (a planner that reads a refiner is labelled
    ``PLANNER@REFINER`` there)."""
    return label == planner or label.startswith(f"{planner}@")


MISSING: dict[str, Any] = dict.fromkeys(
    ("coverage", "floor", "ceiling", "margin", "ceiling_margin", "captured", "views_to_0.95", "views_to_0.99")
)
"""A margin row where evaluate had none (the planner never had a coverage at that budget)."""


def margin_of(report: dict[str, Any], planner: str, views: int, object_name: str = "all") -> dict[str, Any]:
    """The margin row of ``planner`` at ``views`` for one object (``all``: over the objects)."""
    return next(
        (
            r
            for r in report["margins"]
            if same_planner(r["planner"], planner) and r["views"] == views and r["object"] == object_name
        ),
        MISSING,
    )


def own_count(report: dict[str, Any], planner: str) -> dict[str, float]:
    """A one-shot planner at its own view count: coverage, views and its margin over the better of the
    fixed and spread plans at that count, run by run (means over objects of the per-object means)."""
    per_object: dict[str, list[tuple[float, float, float]]] = {}
    for episode in report["runs"]:
        if episode["planner"] != planner:
            continue
        floors = [episode[k] for k in ("matched_fixed_coverage", "matched_spread_coverage") if episode[k] is not None]
        if not floors:
            continue
        coverage = float(episode["coverage"])
        per_object.setdefault(episode["object_name"], []).append(
            (coverage, float(len(episode["visited"])), coverage - max(floors))
        )
    if not per_object:
        return {"coverage": math.nan, "views": math.nan, "over_floor": math.nan, "objects_below": math.nan}
    means = [tuple(mean(column) for column in zip(*runs, strict=True)) for runs in per_object.values()]
    return {
        "coverage": mean(m[0] for m in means),
        "views": mean(m[1] for m in means),
        "over_floor": mean(m[2] for m in means),
        "objects_below": float(sum(1 for m in means if m[2] < 0)),
    }


def rows_of(report: dict[str, Any], trained: list[tuple[Point, Path, dict[str, Any]]]) -> list[dict[str, Any]]:
    rows = []
    for point, checkpoint, record in trained:
        planner = planner_of(point, checkpoint)
        margins = {views: margin_of(report, planner, views) for views in BUDGETS}
        row: dict[str, Any] = {"point": point.name, "family": point.family, **record, "margins": margins}
        if FAMILIES[point.family].one_shot:
            row["own_count"] = own_count(report, planner)
        rows.append(row)
    return rows


def _cell(value: float | None, form: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, form)


def markdown(rows: list[dict[str, Any]], report: dict[str, Any]) -> list[str]:
    room = {views: margin_of(report, "gain", views) for views in BUDGETS}
    lines = [
        "The room (means over the unseen objects, coverage %):",
        "",
        "| views | floor (better of fixed and spread) | ceiling (gain) | ceiling margin, points |",
        "|---:|---:|---:|---:|",
    ]
    for views, row in room.items():
        lines.append(
            f"| {views} | {_cell(row['floor'], '.2f')} | {_cell(row['ceiling'], '.2f')} | "
            f"{_cell(row['ceiling_margin'], '.2f')} |"
        )
    heads = " | ".join(f"captured at {v} (margin)" for v in BUDGETS)
    lines += [
        "",
        f"| point | training objects | training samples | epochs | held out | train min | {heads} | views to 0.95 |",
        "|---|---:|---:|---:|---|---:|" + "---:|" * len(BUDGETS) + "---:|",
    ]
    for row in rows:
        cells = []
        for views in BUDGETS:
            margin = row["margins"][views]
            captured = margin["captured"]
            cells.append(f"{_cell(captured, '.0%')} ({_cell(margin['margin'], '+.2f')})")
        reach = row["margins"][BUDGETS[-1]].get("views_to_0.95")
        metric, value = row["held_out"]
        lines.append(
            f"| {row['point']} | {row['objects']} | {row['samples']} | {row['epochs']} | {metric} {value:.3f} | "
            f"{row['train_seconds'] / 60:.0f} | " + " | ".join(cells) + f" | {_cell(reach, '.2f')} |"
        )
    gain_reach = room[BUDGETS[-1]].get("views_to_0.95")
    lines += ["", f"The ceiling's views to 0.95: {_cell(gain_reach, '.2f')}."]
    one_shot = [row for row in rows if "own_count" in row]
    if one_shot:
        lines += [
            "",
            "One-shot planners at their own view count, against the better of the fixed and spread plans at that",
            "count in the same run (means over objects):",
            "",
            "| point | coverage % | views | over the better of fixed and spread, points | objects below it |",
            "|---|---:|---:|---:|---:|",
        ]
        for row in one_shot:
            own = row["own_count"]
            lines.append(
                f"| {row['point']} | {_cell(own['coverage'], '.2f')} | {_cell(own['views'], '.2f')} | "
                f"{_cell(own['over_floor'], '+.2f')} | {_cell(own['objects_below'], '.0f')} |"
            )
    return lines


def per_object(report: dict[str, Any], planners: dict[str, str]) -> list[str]:
    """Per unseen object: the ceiling's margin and each named planner's at every budget."""
    objects = sorted({r["object"] for r in report["margins"] if r["object"] != "all"})
    heads = ["gain", *planners]
    lines = ["| object | views | " + " | ".join(f"{h} margin" for h in heads) + " |"]
    lines.append("|---|---:|" + "---:|" * len(heads))
    for name in objects:
        for views in BUDGETS:
            cells = []
            for label in heads:
                spec = "gain" if label == "gain" else planners[label]
                row = margin_of(report, spec, views, name)
                key = "ceiling_margin" if label == "gain" else "margin"
                cells.append(_cell(row[key], "+.2f"))
            lines.append(f"| {name} | {views} | " + " | ".join(cells) + " |")
    return lines


def draw(rows: list[dict[str, Any]], path: Path) -> None:
    """Captured share against training objects, one panel per budget, a line per family."""
    figure = Figure(figsize=(12, 3.8), dpi=100)
    families = sorted({row["family"] for row in rows})
    for column, views in enumerate(BUDGETS):
        axes = figure.add_subplot(1, len(BUDGETS), column + 1)
        for family in families:
            line = sorted((r for r in rows if r["family"] == family), key=lambda r: r["objects"])
            shares = [r["margins"][views]["captured"] for r in line]
            axes.plot([r["objects"] for r in line], [math.nan if s is None else 100 * s for s in shares], "o-")
            axes.lines[-1].set_label(family)
        axes.axhline(0, color="grey", linewidth=0.8)
        axes.axhline(100, color="grey", linewidth=0.8, linestyle="--")
        counts = [r["objects"] for r in rows]
        axes.set_xscale("log")
        axes.set_xlim(min(counts) / 1.3, max(counts) * 1.3)
        axes.set_xlabel("training objects")
        axes.set_ylabel("captured share of the ceiling's margin, %")
        axes.set_title(f"{views} views")
        axes.grid(True, alpha=0.3)
        axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)


def parse_counts(text: str) -> list[int | None]:
    return [None if part == "all" else int(part) for part in text.split(",") if part]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--work", type=Path, required=True, help="work folder (runs resume from it)")
    parser.add_argument("--config", type=Path, required=True, help="the evaluation's generation config")
    parser.add_argument(
        "--data", action="append", required=True, metavar="FAMILY=URL", help=f"families: {', '.join(FAMILIES)}"
    )
    parser.add_argument("--objects", default="37,150,all", help="training object counts ('all': the whole side)")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per training run")
    parser.add_argument("--parallel", type=int, default=2, help="training runs side by side")
    parser.add_argument("--val-fraction", type=float, default=0.03)
    parser.add_argument("--workers", type=int, default=2, help="objects evaluated side by side")
    parser.add_argument("--eval-objects", type=Path, default=WATERTIGHT)
    parser.add_argument(
        "--eval-name", default="evaluate", help="the evaluation's cache in --work (another for another --eval-objects)"
    )
    parser.add_argument("--train-only", action="store_true", help="train the points, then stop (evaluate later)")
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    datasets: dict[str, str] = {}
    for item in args.data:
        family, _, url = item.partition("=")
        if family not in FAMILIES or not url:
            parser.error(f"--data {item!r}: give FAMILY=URL with FAMILY one of {', '.join(FAMILIES)}")
        datasets[family] = url
    args.work.mkdir(parents=True, exist_ok=True)
    points = points_of(datasets, parse_counts(args.objects))

    def one(point: Point) -> Path:
        return train_point(point, args.work, args.steps, args.threads, args.val_fraction)

    with ThreadPoolExecutor(max_workers=max(1, args.parallel)) as pool:
        checkpoints = list(pool.map(one, points))
    if args.train_only:
        return 0
    trained = []
    for point, checkpoint in zip(points, checkpoints, strict=True):
        record = trained_on(checkpoint)
        seconds = json.loads((checkpoint.parent / "done").read_text())["seconds"]
        trained.append((point, checkpoint, {**record, "train_seconds": seconds}))
    planners = [planner_of(point, checkpoint) for point, checkpoint in zip(points, checkpoints, strict=True)]
    fixed_from = next(iter(datasets.values()))
    report = evaluate(planners, args.work, args.config, args.eval_objects, fixed_from, args.workers, args.eval_name)
    rows = rows_of(report, trained)
    (args.work / f"{args.eval_name}-curve.json").write_text(json.dumps(rows, indent=1) + "\n")
    largest: dict[str, tuple[str, int]] = {}
    for point, checkpoint, record in trained:
        if point.family not in largest or record["objects"] > largest[point.family][1]:
            largest[point.family] = (planner_of(point, checkpoint), record["objects"])
    lines = markdown(rows, report)
    lines += ["", "Margins over the floor per unseen object, the largest point of each family:", ""]
    lines += per_object(report, {f"{family}-{count}": spec for family, (spec, count) in largest.items()})
    print("\n".join(lines))
    if args.out is not None:
        write_markdown(args.out, "studies.planners.curve_ceiling", argv, lines)
        draw(rows, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
