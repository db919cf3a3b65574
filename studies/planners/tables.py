"""Benchmark: the AIR-OSVP paper's Tables II and III from one dataset: every planner family trained on
the same shards, played on the six unseen watertight meshes beside the floors and the ceilings.

    python -m studies.planners.tables --train WORK/train-v3 \\
        --planner osvp+tuned:WORK/osvp/best.pt --name osvp+tuned:WORK/osvp/best.pt=AIR-OSVP-style ... \\
        --budget 6 --out studies/planners/results/tables.md --png studies/planners/results/tables.png

One `datagen evaluate` (`studies.planners.runs.unseen`: rotations 0 and 4 of 8, initial views 0, 8,
16 and 24, 48 runs per row), the fixed plans chosen from ``--train``. Beside the trained planners
(``--name SPEC=LABEL`` names them): the dataset's own labels played perfectly (``oracle``, the set-cover family's
ceiling), the true gains played step by step (``gain``, the next-best-view family's ceiling: its dense
labels played perfectly), and the floors at every view count from 2 to 10 in all: the best fixed view
set of the training data (``fixed:K``) and random views (``random:K``).

- Table II: each planner at its own count. A next-best-view planner (a checkpoint of a next-view
  target) visits 10 views in all, as NBVNet and PCNBV were played; a one-shot planner takes what it
  decodes. Lifts are evaluate's own, run by run, over the fixed set, spread and random views at the
  planner's count.
- Table III: every planner held to ``--budget`` views in all (the paper holds everyone to AIR-OSVP's
  5.8). `datagen evaluate --budget-views K` keeps the first K views of a run's visiting order, so a
  run's coverage and movement at K are read from the same runs (its coverage after K views, the
  moves between them: a test checks this against a budgeted evaluation); a next-best-view planner's
  play does not depend on its budget. Lifts are over ``fixed:K`` and ``random:K`` in the same
  situation.
- The lift over the fixed plan at every budget from 2 to 10 views: a planner counts only by what it
  gains over a constant plan at the same count.

Printed, and written to ``--out`` with the command, beside the paper's own rows, with a picture of
coverage against views per planner (``--png``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import add_report_options, check_report
from studies.planners.runs import pm, unseen, write_markdown

PAPER = {
    2: [
        ("NBVNet (NBV)", "93.98 ± 9.19", "10", "5.15 ± 0.50"),
        ("PCNBV (NBV)", "96.58 ± 3.87", "10", "4.97 ± 0.49"),
        ("MA-SCVP (one shot + NBV)", "96.59 ± 4.07", "12.40 ± 1.26", "3.32 ± 0.23"),
        ("SCVP (one shot)", "88.69 ± 13.89", "9.60 ± 0.70", "2.15 ± 0.09"),
        ("AIR-OSVP (one shot)", "90.00 ± 4.57", "5.80 ± 1.03", "1.59 ± 0.19"),
    ],
    3: [
        ("PCNBV (NBV)", "92.47 ± 4.97", "5.80", "2.87"),
        ("MA-SCVP", "82.47", "5.80", "-"),
        ("SCVP", "75.77", "5.80", "-"),
        ("AIR-OSVP (one shot)", "90.00 ± 4.57", "5.80 ± 1.03", "1.59 ± 0.19"),
    ],
}
"""The AIR-OSVP paper's rows (its Tables II and III, its 10 test objects), as it prints them."""

CEILINGS = ("oracle", "gain")
FLOOR_COUNTS = tuple(range(2, 11))
"""View counts in all at which the floors are played."""
FLOORS = ("fixed", "random")

Run = dict[str, Any]


def planners_of(trained: Sequence[str]) -> list[str]:
    """Every planner of the evaluation: the trained ones, the two ceilings, the floors at 2 to 10 views."""
    return [*trained, *CEILINGS, *(f"{kind}:{k}" for kind in FLOORS for k in FLOOR_COUNTS)]


def is_floor(planner: str) -> bool:
    return planner.startswith(tuple(f"{kind}:" for kind in FLOORS))


def table_two(report: dict[str, Any], names: dict[str, str]) -> list[str]:
    """Each planner at its own count, with evaluate's run-by-run lifts, then the paper's rows."""
    head = (
        "| planner | coverage % | views | movement m | lift over fixed % | lift over spread % | lift over random % "
        "| objects below fixed |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    below = _objects_below(report["per_object"])
    for row in report["rows"]:
        if is_floor(row["planner"]):
            continue
        name = names.get(row["planner"], row["planner"])
        cells = [name, pm(row, "coverage"), pm(row, "views"), pm(row, "movement")]
        cells += [pm(row, "lift_fixed"), pm(row, "lift_spread"), pm(row, "lift")]
        cells.append(str(below[row["planner"]]) if row["planner"] in below else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return lines + _paper(2)


def _paper(table: int) -> list[str]:
    lines = ["", "The paper's rows (its 10 test objects):", "", "| planner | coverage % | views | movement m |"]
    lines.append("|---|---|---|---|")
    return lines + [f"| {name} | {coverage} | {views} | {moves} |" for name, coverage, views, moves in PAPER[table]]


def _objects_below(per_object: list[dict[str, Any]]) -> dict[str, int]:
    found: dict[str, int] = {}
    for row in per_object:
        if row.get("lift_fixed") is not None:
            found[row["planner"]] = found.get(row["planner"], 0) + int(row["lift_fixed"] < 0)
    return found


def at_budget(run: Run, views: int) -> tuple[float, int, float]:
    """(coverage %, views, movement m) of a run held to ``views`` in all: what `datagen evaluate
    --budget-views` reports for it, the first views of its visiting order."""
    kept = min(views, len(run["coverage_curve"]))
    return 100.0 * run["coverage_curve"][kept - 1], kept, float(sum(run["step_metres"][: kept - 1]))


def _situation(run: Run) -> tuple[str, int, int]:
    return run["object_name"], run["rotation"], run["initial_view"]


def budget_rows(report: dict[str, Any], views: int) -> dict[str, dict[str, list[float]]]:
    """planner -> figure -> per-object means at ``views`` in all: coverage, views, movement and the
    lifts over ``fixed:views`` and ``random:views`` in the same situation."""
    floors = {kind: {_situation(r): r for r in report["runs"] if r["planner"] == f"{kind}:{views}"} for kind in FLOORS}
    per: dict[str, dict[str, dict[str, list[float]]]] = {}
    for run in report["runs"]:
        if is_floor(run["planner"]):
            continue
        coverage, kept, moved = at_budget(run, views)
        figures = {"coverage": coverage, "views": float(kept), "movement": moved}
        for kind, found in floors.items():
            floor = found.get(_situation(run))
            if floor is not None:
                figures[f"lift_{kind}"] = coverage - 100.0 * floor["coverage_curve"][-1]
        objects = per.setdefault(run["planner"], {})
        for key, value in figures.items():
            objects.setdefault(key, {}).setdefault(run["object_name"], []).append(value)
    means: dict[str, dict[str, list[float]]] = {}
    for planner, by_figure in per.items():
        means[planner] = {
            key: [float(np.mean(v)) for _, v in sorted(found.items())] for key, found in by_figure.items()
        }
    return means


def _mean_std(values: list[float] | None) -> str:
    if not values:
        return "-"
    return f"{np.mean(values):.2f} ± {np.std(values):.2f}"


def table_three(report: dict[str, Any], names: dict[str, str], views: int) -> list[str]:
    """Every planner held to ``views`` in all, mean ± std over the objects, then the paper's rows."""
    lines = [
        "| planner | coverage % | views | movement m | lift over fixed % | lift over random % | objects below fixed |",
        "|---|---|---|---|---|---|---|",
    ]
    for planner, figures in budget_rows(report, views).items():
        below = sum(1 for lift in figures.get("lift_fixed", []) if lift < 0)
        cells = [names.get(planner, planner), *(_mean_std(figures.get(k)) for k in ("coverage", "views", "movement"))]
        cells += [_mean_std(figures.get("lift_fixed")), _mean_std(figures.get("lift_random")), str(below)]
        lines.append("| " + " | ".join(cells) + " |")
    floors = {kind: next((r for r in report["rows"] if r["planner"] == f"{kind}:{views}"), None) for kind in FLOORS}
    lines += [
        f"| {kind}:{views} | {pm(row, 'coverage')} | {views} | {pm(row, 'movement')} | - | - | - |"
        for kind, row in floors.items()
        if row is not None
    ]
    return lines + _paper(3)


def lift_by_budget(report: dict[str, Any], names: dict[str, str]) -> list[str]:
    """Each planner's mean lift over the fixed plan (points) at every budget of 2 to 10 views in all."""
    lines = ["| planner | " + " | ".join(str(k) for k in FLOOR_COUNTS) + " |", "|---|" + "---|" * len(FLOOR_COUNTS)]
    by_count = {k: budget_rows(report, k) for k in FLOOR_COUNTS}
    for planner in by_count[FLOOR_COUNTS[0]]:
        cells = [f"{np.mean(by_count[k][planner].get('lift_fixed', [np.nan])):+.2f}" for k in FLOOR_COUNTS]
        lines.append(f"| {names.get(planner, planner)} | " + " | ".join(cells) + " |")
    return lines


def coverage_curves(report: dict[str, Any]) -> dict[str, np.ndarray]:
    """planner -> mean coverage % after 1, 2, ... views over its runs (a run that stopped keeps its last value)."""
    runs: dict[str, list[list[float]]] = {}
    for run in report["runs"]:
        if not is_floor(run["planner"]):
            runs.setdefault(run["planner"], []).append(list(run["coverage_curve"]))
    curves = {}
    for planner, found in runs.items():
        longest = max(len(c) for c in found)
        padded = np.array([c + [c[-1]] * (longest - len(c)) for c in found], dtype=np.float64)
        curves[planner] = 100.0 * padded.mean(axis=0)
    return curves


def floor_curves(report: dict[str, Any]) -> dict[str, tuple[list[int], list[float]]]:
    """fixed and random: (view counts, mean coverage %) from their rows."""
    found: dict[str, tuple[list[int], list[float]]] = {}
    for kind in FLOORS:
        rows = {int(r["planner"].split(":")[1]): r for r in report["rows"] if r["planner"].startswith(f"{kind}:")}
        counts = sorted(rows)
        found[kind] = (counts, [rows[k]["coverage"] for k in counts])
    return found


def draw(report: dict[str, Any], names: dict[str, str], path: Path, title: str) -> None:
    """Coverage against views in all: one line per planner (mean over its runs), the floors dotted."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8.5, 5.5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.subplots()
    for planner, curve in coverage_curves(report).items():
        style = "--" if planner in CEILINGS else "-"
        axes.plot(np.arange(1, curve.size + 1), curve, style, marker=".", label=names.get(planner, planner))
    for kind, (counts, coverage) in floor_curves(report).items():
        axes.plot(counts, coverage, ":", marker="x", color="grey" if kind == "random" else "black", label=f"{kind}:K")
    axes.set_xlabel("views in all (the initial view included)")
    axes.set_ylabel("surface coverage %")
    axes.set_title(title)
    axes.grid(alpha=0.3)
    axes.legend(loc="lower right", fontsize="small")
    figure.tight_layout()
    figure.savefig(path)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--train", required=True, help="the training dataset (the fixed plans are chosen from it)")
    parser.add_argument("--planner", action="append", default=[], help="a trained planner spec (repeatable)")
    parser.add_argument("--name", action="append", default=[], help="SPEC=LABEL: how a planner is named in the tables")
    parser.add_argument("--budget", type=int, default=6, help="Table III: views in all every planner is held to")
    parser.add_argument("--config", type=Path, help="the evaluation's config (e.g. the training set's poco_version)")
    parser.add_argument("--workers", type=int, default=2)
    add_report_options(parser, None, "write the tables as Markdown here")
    parser.add_argument("--png", type=Path, help="draw coverage against views here")
    parser.add_argument("--json", type=Path, help="keep evaluate's whole report here")
    parser.add_argument("--report", type=Path, help="the tables from a report kept with --json, without evaluating")
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    if args.budget not in FLOOR_COUNTS:
        parser.error(f"--budget {args.budget}: give 2 to 10 views in all")
    names = dict(pair.rsplit("=", 1) for pair in args.name)
    if args.report:
        report = json.loads(args.report.read_text())
    else:
        with tempfile.TemporaryDirectory() as folder:
            extra = ["--workers", str(args.workers), *(["--config", str(args.config)] if args.config else [])]
            report = unseen(planners_of(args.planner), Path(folder), "tables", fixed_from=args.train, extra=extra)
    if args.json:
        args.json.write_text(json.dumps(report))
    lines = ["## Table II: every planner at its own view count", "", *table_two(report, names), ""]
    lines += [f"## Table III: every planner held to {args.budget} views in all", ""]
    lines += [*table_three(report, names, args.budget), ""]
    lines += ["## Lift over the best fixed plan at every budget (views in all; points, mean over objects)", ""]
    lines += lift_by_budget(report, names)
    if args.png:
        draw(report, names, args.png, "six unseen meshes, 48 runs per planner")
        lines += ["", f"![coverage against views]({args.png.name})"]
    print("\n".join(lines))
    if args.out:
        write_markdown(args.out, "studies.planners.tables", argv, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
