"""Judge planners on real objects they never saw (issue 49): the captured share of the room between the
floor and the ceiling, overall, per source folder and per kind of object.

    python -m studies.planners.real_objects.judge --set test --fixed-from WORK/real-train-none \\
        --planner nbv=shipped:nbv --planner one-shot=shipped:oneshot [--work WORK/judge] \\
        [--margins 2,3,4,6] [--workers 2] --out studies/planners/real_objects/results/judge-test.md [--replace]

One `datagen evaluate --margins` per evaluation set plays every planner beside the ceiling (``gain``:
the true gains played step by step) and the floor's two plans (``fixed``, chosen on the training
dataset ``--fixed-from``, and ``spread``), on rotations 0 and 4 of 8 from initial views 0, 8, 16 and
24 of every object, so eight situations an object. Sets: ``test`` and ``val`` (the real-object
split beside this script), ``six`` (the six watertight shared meshes) and ``high`` (the eight shared
meshes with the most room). The evaluation's JSON is kept in ``--work``, so the report is written
again without playing again.

Reported per planner and budget: coverage, floor, ceiling, the planner's margin over the floor and
the ceiling's (the room), and the captured share (the ratio of the mean margins over objects); for a
one-shot planner also its coverage at its own view count against the better of the fixed and spread
plans there, run by run. Then the captured share per source folder (ycb, kit, household, meshes) and
per kind of object, from the prepared mesh: ``flat`` (thinnest principal extent under 30 % of the
largest), ``long`` (largest over the middle one above 2), ``compact`` otherwise, and open (not
watertight) against closed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from statistics import mean
from typing import Any

import numpy as np

from benchmarks.common import REPO_ROOT, add_report_options, check_report
from studies.planners.curve_ceiling import own_count, same_planner
from studies.planners.runs import run, write_markdown

HERE = Path(__file__).resolve().parent
SETS = {
    "test": HERE / "test.txt",
    "val": HERE / "val.txt",
    "six": REPO_ROOT / "examples" / "watertight-meshes.txt",
    "high": REPO_ROOT / "examples" / "high-ceiling-meshes.txt",
}
MARGINS = (2, 3, 4, 6)
FLAT, LONG = 0.3, 2.0


def evaluate(
    objects: Path,
    planners: Sequence[str],
    fixed_from: str,
    margins: Sequence[int],
    workers: int,
    work: Path,
    config: Path | None = None,
) -> dict[str, Any]:
    """One `datagen evaluate --json --margins` of ``planners`` beside the ceiling and the floor, cached in ``work``."""
    command = ["datagen", "evaluate", "--objects", str(objects), "--rotations", "0,4", "--initial-views", "0,8,16,24"]
    command += ["--fixed-from", fixed_from, "-p", "gain", "-p", "fixed", "-p", "spread"]
    command += ["--margins", ",".join(map(str, margins)), "--workers", str(workers), "--json"]
    command += [part for planner in planners for part in ("-p", planner)]
    if config is not None:  # a planner trained at other rotations is still judged at 0 and 4 of 8
        command += ["--config", str(config)]
    key = hashlib.sha256(json.dumps(command[1:]).encode()).hexdigest()[:16]
    work.mkdir(parents=True, exist_ok=True)
    cache = work / f"evaluate-{objects.stem}-{key}.json"
    if cache.exists():
        return dict(json.loads(cache.read_text()))
    found = json.loads(run(command, work / f"evaluate-{objects.stem}-{key}.log"))
    cache.write_text(json.dumps(found) + "\n")
    return dict(found)


def object_facts(objects: Path) -> dict[str, dict[str, str]]:
    """Per object name: its source folder and kind (`FLAT`, `LONG`), and open or closed."""
    from datagen.pipeline.objects.objects_file import read_objects_file
    from datagen.pipeline.objects.prepare import prepare_object
    from schemas.config import GenerationConfig

    config = GenerationConfig()
    facts = {}
    for spec in read_objects_file(objects).objects:
        prepared = prepare_object(spec, config)
        centred = prepared.vertices - prepared.vertices.mean(axis=0)
        axes = np.linalg.svd(centred, full_matrices=False)[2]
        small, middle, large = np.sort(np.ptp(centred @ axes.T, axis=0))
        kind = "flat" if small < FLAT * large else "long" if large > LONG * middle else "compact"
        facts[spec.name] = {
            "folder": Path(spec.source).parent.name,
            "kind": kind,
            "closure": "closed" if prepared.watertight else "open",
        }
    return facts


def margin_rows(report: dict[str, Any], planner: str, views: int) -> list[dict[str, Any]]:
    """Per-object margin rows of ``planner`` at ``views`` (not the ``all`` row)."""
    return [
        r
        for r in report["margins"]
        if same_planner(r["planner"], planner) and r["views"] == views and r["object"] != "all"
    ]


def grouped_share(rows: list[dict[str, Any]]) -> tuple[float, float, float, int]:
    """(captured, mean margin, mean room, objects) over ``rows``: the ratio of the mean margins, as evaluate's."""
    kept = [r for r in rows if r["margin"] is not None and r["ceiling_margin"] is not None]
    if not kept:
        return math.nan, math.nan, math.nan, 0
    margin, room = mean(r["margin"] for r in kept), mean(r["ceiling_margin"] for r in kept)
    return (margin / room if room > 1e-9 else math.nan), margin, room, len(kept)


def _share(value: float) -> str:
    return "-" if math.isnan(value) else f"{100 * value:+.0f} %"


def overall(report: dict[str, Any], planners: dict[str, str], margins: Sequence[int]) -> list[str]:
    lines = [
        "| planner | views | coverage % | floor % | ceiling % | margin | room | captured |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, spec in planners.items():
        for views in margins:
            row = next(
                (
                    r
                    for r in report["margins"]
                    if same_planner(r["planner"], spec) and r["views"] == views and r["object"] == "all"
                ),
                None,
            )
            if row is None or row["coverage"] is None:
                lines.append(f"| {name} | {views} | - | - | - | - | - | - |")
                continue
            captured = math.nan if row["captured"] is None else row["captured"]
            lines.append(
                f"| {name} | {views} | {row['coverage']:.2f} | {row['floor']:.2f} | {row['ceiling']:.2f} | "
                f"{row['margin']:+.2f} | {row['ceiling_margin']:.2f} | {_share(captured)} |"
            )
    return lines


def own_counts(report: dict[str, Any], planners: dict[str, str]) -> list[str]:
    """One-shot planners at their own count against the better of fixed and spread there."""
    lines = []
    for name, spec in planners.items():
        runs = [
            e for e in report["runs"] if e["planner"] == spec and e.get("count_curve") is not None and not e["ordered"]
        ]
        if not runs:
            continue
        found = own_count(report, spec)
        lines.append(
            f"| {name} | {found['views']:.2f} | {found['coverage']:.2f} | {found['over_floor']:+.2f} "
            f"| {found['objects_below']:.0f} |"
        )
    if not lines:
        return []
    head = [
        "| planner | views | coverage % | over the better of fixed and spread (points) | objects below |",
        "|---|---:|---:|---:|---:|",
    ]
    return ["At its own view count:", "", *head, *lines]


def breakdown(
    report: dict[str, Any], planners: dict[str, str], facts: dict[str, dict[str, str]], key: str, margins: Sequence[int]
) -> list[str]:
    groups = sorted({f[key] for f in facts.values()})
    head = "| planner | " + " | ".join(f"{g} ({sum(1 for f in facts.values() if f[key] == g)})" for g in groups) + " |"
    lines = [f"Captured share per {key} at {', '.join(map(str, margins))} views (objects in brackets):", "", head]
    lines.append("|---|" + "---:|" * len(groups))
    for name, spec in planners.items():
        cells = []
        for group in groups:
            shares = []
            for views in margins:
                rows = [r for r in margin_rows(report, spec, views) if facts.get(r["object"], {}).get(key) == group]
                shares.append(_share(grouped_share(rows)[0]))
            cells.append(" / ".join(shares))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--set", choices=sorted(SETS), required=True)
    parser.add_argument("--planner", action="append", required=True, metavar="NAME=SPEC", help="repeatable")
    parser.add_argument("--fixed-from", required=True, help="the training dataset the fixed plans are chosen on")
    parser.add_argument("--margins", default=",".join(map(str, MARGINS)))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--work", type=Path, default=Path("judge-work"))
    parser.add_argument(
        "--config",
        type=Path,
        help="image with this config (8 rotations, the planners' refiner) rather than the first planner's own",
    )
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    planners = dict(pair.split("=", 1) for pair in args.planner)
    margins = [int(v) for v in args.margins.split(",")]
    objects = SETS[args.set]
    report = evaluate(objects, list(planners.values()), args.fixed_from, margins, args.workers, args.work, args.config)
    facts = object_facts(objects)
    lines = [f"# Planners on the {args.set} set ({objects.name}: {len(facts)} objects, 8 situations each)", ""]
    for section in (
        overall(report, planners, margins),
        own_counts(report, planners),
        breakdown(report, planners, facts, "folder", margins),
        breakdown(report, planners, facts, "kind", margins),
        breakdown(report, planners, facts, "closure", margins),
    ):
        lines += [*section, ""]
    per_object: dict[str, list[str]] = defaultdict(list)
    for spec in planners.values():
        for row in margin_rows(report, spec, 4):
            captured = math.nan if row["captured"] is None else row["captured"]
            per_object[row["object"]].append(f"{row['margin']:+.2f} ({_share(captured)})")
    lines += ["", "Per object at 4 views, margin over the floor in points (captured):", ""]
    lines += [
        "| object | folder | kind | room | " + " | ".join(planners) + " |",
        "|---|---|---|---:|" + "---:|" * len(planners),
    ]
    rooms = {r["object"]: r["ceiling_margin"] for r in report["margins"] if r["planner"] == "gain" and r["views"] == 4}
    for name in sorted(per_object):
        fact = facts.get(name, {"folder": "?", "kind": "?"})
        room = rooms.get(name)
        lines.append(
            f"| {name} | {fact['folder']} | {fact['kind']} | {'-' if room is None else f'{room:.2f}'} | "
            + " | ".join(per_object[name])
            + " |"
        )
    write_markdown(args.out, "studies.planners.real_objects.judge", argv, lines)
    print(args.out.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
