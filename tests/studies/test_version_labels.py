"""studies/labels/version_labels.py's comparison on made-up evaluate reports (the evaluations themselves
run `datagen evaluate`, measured by hand: studies/labels/results/version-labels.md)."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def version_labels() -> ModuleType:
    return load_study("labels.version_labels")


def run(name: str, initial: int, visited: list[int], observed: int, planner: str = "oracle") -> dict[str, Any]:
    return {
        "planner": planner,
        "object_name": name,
        "rotation": 0,
        "initial_view": initial,
        "observed_size": observed,
        "reference_size": 200,
        "visited": visited,
        "step_metres": [0.5] * (len(visited) - 1),
    }


def test_runs_are_compared_one_by_one(version_labels: ModuleType) -> None:
    old = version_labels.runs_of(
        {"runs": [run("cow", 0, [0, 3, 7], 180), run("cow", 8, [8, 1], 190), run("cow", 0, [0], 10, "random")]}
    )
    new = version_labels.runs_of({"runs": [run("cow", 0, [0, 7, 3], 180), run("cow", 8, [8, 2, 5], 196)]})
    assert set(old) == {("cow", 0, 0), ("cow", 0, 8)}  # the oracle's runs only
    assert old[("cow", 0, 0)].coverage == pytest.approx(90.0) and old[("cow", 0, 8)].metres == pytest.approx(0.5)
    lines = version_labels.report({"old": old, "new": new})
    assert lines[2] == "| old | 2 | 92.50 | 2.50 | 0.75 |"
    # Run 1: the same views in another order; run 2: other views, 3 points more coverage.
    assert lines[-1] == "| new - old | 2 | +1.50 | 1.50 | +0.50 | 1 |"
