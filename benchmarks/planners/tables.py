"""Benchmark: the AIR-OSVP paper's Tables II and III from one dataset: every planner family trained on
the same shards, played on the six unseen watertight meshes beside the floors and the ceilings.

    python -m benchmarks.planners.tables --train WORK/train-v3 --table 2 \\
        --planner osvp+tuned:WORK/osvp/best.pt --planner osvp:WORK/pcnbv/best.pt \\
        --planner osvp:WORK/nbvnet/best.pt --planner osvp:WORK/scvp/best.pt \\
        --name osvp+tuned:WORK/osvp/best.pt=AIR-OSVP-style ... --out benchmarks/planners/results/tables.md
    python -m benchmarks.planners.tables ... --table 3 --budget 6      # everyone held to 6 views in all

One `datagen evaluate` per table (`benchmarks.planners.runs.unseen`: rotations 0 and 4 of 8, initial
views 0, 8, 16 and 24, 48 runs per row), the fixed plans chosen from ``--train``. Table II plays each
planner at its own count: a next-best-view planner (a checkpoint of a next-view target) visits 10
views in all, as NBVNet and PCNBV were played, a one-shot planner takes what it decodes. Table III
holds every planner to ``--budget`` views in all (`datagen evaluate --budget-views`: a next-best-view
planner plays exactly that many, a one-shot plan is cut to its first views along the path). Beside
the trained planners: the dataset's own labels played perfectly (``oracle``, the set-cover family's
ceiling) and the true gains played step by step (``gain``, the next-best-view family's ceiling: its
dense labels played perfectly). Every trained row carries evaluate's run-by-run lifts over the best
fixed view set, spread views and random views at its own view count: a planner counts only by what
it gains over a constant plan. Printed, and written to ``--out`` with the command, beside the
paper's own rows, with a picture of coverage against views per planner (``--png``).
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

from benchmarks.planners.runs import pm, unseen

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
"""The AIR-OSVP paper's rows (its Tables II and III, its 10 test objects; ../shared/reference/planner-families.md)."""

CEILINGS = ("oracle", "gain")


def planners_of(table: int, trained: Sequence[str], budget: int | None) -> list[str]:
    """The evaluate planners of a table: the trained ones, the two ceilings and, at a budget, the floors at it."""
    ceilings = [*CEILINGS]
    floors = [f"fixed:{budget}", f"spread:{budget}", f"random:{budget}"] if table == 3 and budget else []
    return [*trained, *ceilings, *floors]


def table_lines(report: dict[str, Any], names: dict[str, str], table: int) -> list[str]:
    """Our rows (coverage, views, movement, lifts over fixed, spread and random at equal views), then the paper's."""
    head = (
        "| planner | coverage % | views | movement m | lift over fixed % | lift over spread % | lift over random % "
        "| objects below fixed |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    below = _objects_below_fixed(report)
    for row in report["rows"]:
        name = names.get(row["planner"], row["planner"])
        cells = [name, pm(row, "coverage"), pm(row, "views"), pm(row, "movement")]
        cells += [pm(row, "lift_fixed"), pm(row, "lift_spread"), pm(row, "lift")]
        cells.append(str(below[row["planner"]]) if row["planner"] in below else "-")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "The paper's rows (its 10 test objects):", "", "| planner | coverage % | views | movement m |"]
    lines.append("|---|---|---|---|")
    lines += [f"| {name} | {coverage} | {views} | {movement} |" for name, coverage, views, movement in PAPER[table]]
    return lines


def _objects_below_fixed(report: dict[str, Any]) -> dict[str, int]:
    found: dict[str, int] = {}
    for row in report["per_object"]:
        if row.get("lift_fixed") is not None:
            found[row["planner"]] = found.get(row["planner"], 0) + int(row["lift_fixed"] < 0)
    return found


def coverage_curves(report: dict[str, Any]) -> dict[str, np.ndarray]:
    """planner -> mean coverage % after 1, 2, ... views over its runs (a run that stopped keeps its last value)."""
    runs: dict[str, list[list[float]]] = {}
    for run in report["runs"]:
        runs.setdefault(run["planner"], []).append(list(run["coverage_curve"]))
    curves = {}
    for planner, found in runs.items():
        longest = max(len(c) for c in found)
        padded = np.array([c + [c[-1]] * (longest - len(c)) for c in found], dtype=np.float64)
        curves[planner] = 100.0 * padded.mean(axis=0)
    return curves


def draw(report: dict[str, Any], names: dict[str, str], path: Path, title: str) -> None:
    """Coverage against views in all, one line per planner (mean over its runs)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8.0, 5.5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.subplots()
    for planner, curve in coverage_curves(report).items():
        style = ":" if planner.startswith(("fixed", "spread", "random")) else "--" if planner in CEILINGS else "-"
        axes.plot(np.arange(1, curve.size + 1), curve, style, marker=".", label=names.get(planner, planner))
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
    parser.add_argument("--table", type=int, choices=(2, 3), required=True)
    parser.add_argument("--planner", action="append", default=[], help="a trained planner spec (repeatable)")
    parser.add_argument("--name", action="append", default=[], help="SPEC=LABEL: how a planner is named in the table")
    parser.add_argument("--budget", type=int, help="Table III: views in all every planner is held to")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, help="write the table as Markdown here")
    parser.add_argument("--png", type=Path, help="draw coverage against views here")
    parser.add_argument("--json", type=Path, help="keep evaluate's whole report here")
    parser.add_argument("--report", type=Path, help="the table from a report kept with --json, without evaluating")
    args = parser.parse_args(argv)
    if args.table == 3 and not args.budget:
        parser.error("--table 3 needs --budget K (views in all)")
    names = dict(pair.rsplit("=", 1) for pair in args.name)
    extra = ["--workers", str(args.workers), *(["--budget-views", str(args.budget)] if args.table == 3 else [])]
    if args.report:
        report = json.loads(args.report.read_text())
    else:
        planners = planners_of(args.table, args.planner, args.budget)
        with tempfile.TemporaryDirectory() as folder:
            report = unseen(planners, Path(folder), f"table-{args.table}", fixed_from=args.train, extra=extra)
    if args.json:
        args.json.write_text(json.dumps(report))
    title = "Table II: own view counts" if args.table == 2 else f"Table III: {args.budget} views in all"
    lines = [f"## {title}", "", *table_lines(report, names, args.table)]
    if args.png:
        draw(report, names, args.png, f"{title}, six unseen meshes")
        lines += ["", f"![coverage against views]({args.png.name})"]
    print("\n".join(lines))
    if args.out:
        command = "python -m benchmarks.planners.tables " + " ".join(argv if argv is not None else sys.argv[1:])
        args.out.write_text("\n".join([f"Made by `{command}`.", "", *lines, ""]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
