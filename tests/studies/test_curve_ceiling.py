"""studies/planners/curve_ceiling.py's reading of a `datagen evaluate --json` report, on made-up
runs (the margins themselves are `datagen evaluate --margins`, tested in tests/evaluate/test_margins.py):
a planner that reads a refiner is found under its ``@REFINER`` label, and a one-shot planner is judged
at its own count against the better of the fixed and spread plans run by run, computed here by hand."""

from __future__ import annotations

from types import ModuleType

import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def curve() -> ModuleType:
    return load_study("planners.curve_ceiling")


def run(name: str, coverage: float, views: int, fixed: float | None, spread: float | None) -> dict[str, object]:
    return {
        "planner": "osvp+tuned:x.pt",
        "object_name": name,
        "coverage": coverage,
        "visited": list(range(views)),
        "matched_fixed_coverage": fixed,
        "matched_spread_coverage": spread,
    }


def test_own_count_is_judged_against_the_better_plan_run_by_run(curve: ModuleType) -> None:
    report = {
        "runs": [
            run("cow", 90.0, 4, fixed=88.0, spread=91.0),  # -1: spread is the better plan here
            run("cow", 95.0, 5, fixed=92.0, spread=90.0),  # +3
            run("horse", 80.0, 3, fixed=85.0, spread=None),  # -5: fixed alone
            run("horse", 70.0, 3, fixed=None, spread=None),  # no plan to judge against: left out
            {**run("horse", 10.0, 2, 0.0, 0.0), "planner": "gain"},  # another planner
        ]
    }
    found = curve.own_count(report, "osvp+tuned:x.pt")
    # per object first (cow: coverage 92.5, views 4.5, margin +1; horse: 80, 3, -5), then over objects
    assert found == {"coverage": (92.5 + 80.0) / 2, "views": (4.5 + 3.0) / 2, "over_floor": -2.0, "objects_below": 1.0}
    missing = curve.own_count(report, "osvp+tuned:other.pt")
    assert all(value != value for value in missing.values())  # NaN where the planner never ran


def test_a_margin_row_is_found_under_its_refiner_label(curve: ModuleType) -> None:
    rows = [
        {"object": "all", "planner": "osvp+tuned:x.pt@none", "views": 4, "captured": 0.5},
        {"object": "all", "planner": "osvp+tuned:x.pt.old", "views": 4, "captured": 0.9},
        {"object": "cow", "planner": "osvp:n.pt", "views": 4, "captured": 0.25},
    ]
    report = {"margins": rows}
    assert curve.margin_of(report, "osvp+tuned:x.pt", 4)["captured"] == 0.5
    assert curve.margin_of(report, "osvp:n.pt", 4, "cow")["captured"] == 0.25
    assert curve.margin_of(report, "osvp:n.pt", 4)["captured"] is None  # no row over all objects
    assert curve.parse_counts("37,150,all") == [37, 150, None]
