"""studies/planners/label_margin.py's tables on a made-up `datagen evaluate --json` report (the
evaluation itself is measured by hand: studies/planners/results/label-margin.md)."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def label_margin() -> ModuleType:
    return load_study("planners.label_margin")


def row(planner: str, coverage: float, lift_fixed: float | None, obj: str | None = None) -> dict[str, Any]:
    found: dict[str, Any] = {"planner": planner, "coverage": coverage, "coverage_std": 1.0, "views": 2.0}
    found.update(views_std=0.0, movement=0.7, movement_std=0.1, lift=5.0, lift_std=1.0, views_to_tau=None)
    found.update(lift_spread=None)
    found.update(lift_fixed=lift_fixed, lift_fixed_std=None if lift_fixed is None else 2.0)
    if obj is not None:
        found["object"] = obj
    return found


REPORT = {
    "fixed": {
        "source": "train",
        "tasks": 3,
        "cases": 96,
        "plans": {"1": {"views": [21], "mean_coverage": 0.7, "exact": True}},
    },
    "tau": None,
    "rows": [
        row("oracle", 90.0, -1.0),
        row("oracle:budget=1", 75.0, 14.0),
        row("osvp+topk=1:x", 70.0, 7.0),
        row("fixed:2", 61.0, None),
    ],
    "per_object": [
        row("oracle", 90.0, 2.0, "cow"),
        row("oracle", 90.0, -4.0, "spot"),
        row("oracle:budget=1", 75.0, 12.0, "cow"),
        row("oracle:budget=1", 75.0, 16.0, "spot"),
        row("osvp+topk=1:x", 70.0, 7.0, "cow"),
        row("osvp+topk=1:x", 70.0, 7.0, "spot"),
    ],
}


def test_the_largest_margin_and_the_share_a_planner_captures(label_margin: ModuleType) -> None:
    lines = label_margin.summary(REPORT, ["oracle:budget=1"])
    assert lines[0].count("|") == lines[1].count("|") == lines[2].count("|") == 9
    assert label_margin.summary(REPORT, ["osvp+topk=1:x=oracle"])[-1] == (
        "osvp+topk=1:x: oracle has no margin over fixed to capture (-1.00 points)"
    )
    assert label_margin.summary(REPORT, ["osvp+topk=1:x=oracle:budget=1"])[-1] == (
        "osvp+topk=1:x captures 50% of oracle:budget=1's margin over fixed"
    )
    assert lines[2].startswith(
        "| oracle | 90.00 ± 1.00 | 2.00 ± 0.00 | 0.70 ± 0.10 | -1.00 ± 2.00 | - | 5.00 ± 1.00 | 1 |"
    )
    assert "| fixed:2 | 61.00 ± 1.00 |" in lines[5] and lines[5].endswith("| - | - | 5.00 ± 1.00 | - |")
    assert "largest margin over fixed: oracle:budget=1, +14.00 points (lowest object +12.00)" in lines
    assert "osvp+topk=1:x captures 50% of oracle:budget=1's margin over fixed" in lines


def test_the_margin_per_object(label_margin: ModuleType) -> None:
    assert label_margin.margin_table(REPORT) == [
        "| planner | cow | spot |",
        "|---|---|---|",
        "| oracle | +2.00 | -4.00 |",
        "| oracle:budget=1 | +12.00 | +16.00 |",
        "| osvp+topk=1:x | +7.00 | +7.00 |",
    ]
    assert label_margin.fixed_plans(REPORT)[1] == "- 1 new views: [21] (70.0 % on the training cases, exact)"
