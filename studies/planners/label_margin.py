"""Benchmark: what each label objective's perfect planner gains over the best fixed plan, and what a trained one does.

    python -m studies.planners.label_margin --train WORK/train-data  # every objective's margin
    python -m studies.planners.label_margin --train WORK/train-data --planner osvp+topk=1:RUN/best.pt \\
        --against oracle:budget=1 --tau 0.9 --out studies/planners/results/label-margin.md

One `datagen evaluate` on the six unseen watertight shared meshes (examples/watertight-meshes.txt),
rotations 0 and 4 of 8, initial views 0, 8, 16 and 24 (48 runs per row), the POCO refiner, fixed
plans chosen from the training dataset ``--train`` (`datagen evaluate --fixed-from`). Rows:

- the floor: the best fixed set, data-free spread views and random views at 2-6 views in all;
- each label objective's oracle (the dataset's labels played perfectly, `oracle:SETTING=V`): the
  paper's cover at alpha 10 (the default) and other alphas, max_coverage at budgets 1-4 and
  partial_cover at several tau; every oracle run is judged against the fixed set and random views at
  its own view count in the same situation (evaluate's lifts), so the margin is run by run;
- ``--planner SPEC`` (repeatable): trained planners, judged the same way; with ``--against ORACLE`` (or
  ``--against PLANNER=ORACLE``, repeatable) the share of that oracle's margin over fixed each one
  captures; with ``--tau`` the views each needs to see that share of the surface, beside the fixed
  plan's.

Printed (and written to ``--out`` as Markdown, with the command): the summary table, then the margin
over fixed per object for every oracle and planner, and the objective with the largest margin.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from benchmarks.common import add_report_options, check_report
from studies.planners.runs import pm, unseen, write_markdown

FLOOR = [f"{kind}:{k}" for k in range(2, 7) for kind in ("fixed", "spread", "random")]
ORACLES = [
    "oracle",
    "oracle:alpha=5",
    "oracle:alpha=20",
    "oracle:budget=1",
    "oracle:budget=2",
    "oracle:budget=3",
    "oracle:budget=4",
    "oracle:tau=0.8",
    "oracle:tau=0.85",
    "oracle:tau=0.9",
    "oracle:tau=0.95",
]


def per_object_margins(report: dict[str, object]) -> dict[str, dict[str, float]]:
    """planner -> object -> mean coverage points over the fixed set at equal views."""
    margins: dict[str, dict[str, float]] = {}
    for row in report["per_object"]:  # type: ignore[attr-defined]
        if row["lift_fixed"] is not None:
            margins.setdefault(row["planner"], {})[row["object"]] = row["lift_fixed"]
    return margins


def summary(report: dict[str, object], against: Sequence[str] = ()) -> list[str]:
    rows = {row["planner"]: row for row in report["rows"]}  # type: ignore[attr-defined]
    margins = per_object_margins(report)
    tau = report.get("tau")
    head = (
        "| planner | coverage % | views | movement m | lift over fixed % | lift over spread % | lift over random % "
        "| objects below fixed |"
    )
    lines = [head + (" views to tau |" if tau else ""), "|---|" * 1 + "---|" * 7 + ("---|" if tau else "")]
    for name, row in rows.items():
        below = sum(1 for m in margins.get(name, {}).values() if m < 0)
        cells = [name, pm(row, "coverage"), pm(row, "views"), pm(row, "movement")]
        cells += [
            pm(row, "lift_fixed"),
            pm(row, "lift_spread"),
            pm(row, "lift"),
            str(below) if name in margins else "-",
        ]
        if tau:
            cells.append(pm(row, "views_to_tau"))
        lines.append("| " + " | ".join(cells) + " |")
    oracles = {
        name: row["lift_fixed"]
        for name, row in rows.items()
        if name.startswith("oracle") and row["lift_fixed"] is not None
    }
    if oracles:
        best = max(oracles, key=lambda name: oracles[name])
        worst_object = min(margins[best].values())
        lines += [
            "",
            f"largest margin over fixed: {best}, {oracles[best]:+.2f} points (lowest object {worst_object:+.2f})",
        ]
    for pair in against:  # PLANNER=ORACLE, or ORACLE for every trained planner
        split = pair.rfind("=oracle")
        planner, oracle = (pair[:split], pair[split + 1 :]) if split >= 0 else ("", pair)
        if oracle not in rows or rows[oracle]["lift_fixed"] is None:
            continue
        ceiling = rows[oracle]["lift_fixed"]
        for name, row in rows.items():
            trained = not name.startswith(("oracle", "fixed", "spread", "random"))
            if not trained or row["lift_fixed"] is None or (planner and name != planner):
                continue
            if ceiling > 0:
                lines.append(f"{name} captures {row['lift_fixed'] / ceiling:.0%} of {oracle}'s margin over fixed")
            else:
                lines.append(f"{name}: {oracle} has no margin over fixed to capture ({ceiling:+.2f} points)")
    return lines


def margin_table(report: dict[str, object]) -> list[str]:
    margins = per_object_margins(report)
    objects = sorted({obj for per in margins.values() for obj in per})
    lines = ["| planner | " + " | ".join(objects) + " |", "|---|" + "---|" * len(objects)]
    for name, per in margins.items():
        lines.append(f"| {name} | " + " | ".join(f"{per.get(obj, float('nan')):+.2f}" for obj in objects) + " |")
    return lines


def fixed_plans(report: dict[str, object]) -> list[str]:
    fixed = report["fixed"]
    lines = [f"fixed plans: {fixed['tasks']} tasks, {fixed['cases']} single-view cases of {fixed['source']}"]  # type: ignore[index]
    for size, plan in list(fixed["plans"].items())[:6]:  # type: ignore[index]
        exact = "exact" if plan["exact"] else "greedy"
        lines.append(
            f"- {size} new views: {plan['views']} ({100 * plan['mean_coverage']:.1f} % on the training cases, {exact})"
        )
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--train", required=True, help="the training dataset the fixed plans are chosen from")
    parser.add_argument("--planner", action="append", default=[], help="a trained planner spec (repeatable)")
    parser.add_argument(
        "--against",
        action="append",
        default=[],
        help="ORACLE (every trained planner) or PLANNER=ORACLE: the oracle whose margin a planner's share is of",
    )
    parser.add_argument("--objectives", nargs="*", default=ORACLES, help="oracle specs (default: every objective)")
    parser.add_argument("--no-floor", action="store_true", help="leave out the fixed/spread/random rows at 2-6 views")
    parser.add_argument("--tau", type=float, help="also the views each planner needs to see this share")
    parser.add_argument("--workers", type=int, default=2)
    add_report_options(parser, None, "write the tables as Markdown here")
    parser.add_argument("--json", type=Path, help="keep evaluate's whole report here")
    parser.add_argument("--report", type=Path, help="tables from a report kept with --json, without evaluating")
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    planners = [*args.objectives, *args.planner, *([] if args.no_floor else FLOOR)]
    extra = ["--workers", str(args.workers), *(["--tau", str(args.tau)] if args.tau is not None else [])]
    if args.report:
        report = json.loads(args.report.read_text())
    else:
        with tempfile.TemporaryDirectory() as folder:
            report = unseen(planners, Path(folder), "label-margin", fixed_from=args.train, extra=extra)
    if args.json:
        args.json.write_text(json.dumps(report))
    lines = [
        *fixed_plans(report),
        "",
        *summary(report, args.against),
        "",
        "margin over fixed per object:",
        "",
        *margin_table(report),
    ]
    print("\n".join(lines))
    if args.out:
        write_markdown(args.out, "studies.planners.label_margin", argv, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
