"""benchmarks/planners/tables.py's tables and coverage curves on a made-up `datagen evaluate --json`
report (the evaluation itself is measured by hand: osvp/recipe/RESULTS.md)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from support.benchmarks import load_benchmark


@pytest.fixture(scope="module")
def tables() -> ModuleType:
    return load_benchmark("planners.tables")


def row(planner: str, lift_fixed: float | None, obj: str | None = None) -> dict[str, Any]:
    found: dict[str, Any] = {"planner": planner, "coverage": 90.0, "coverage_std": 1.0, "views": 6.0}
    found.update(views_std=0.5, movement=1.5, movement_std=0.1, lift=4.0, lift_std=1.0, lift_spread=None)
    found.update(lift_fixed=lift_fixed, lift_fixed_std=None if lift_fixed is None else 2.0)
    if obj is not None:
        found["object"] = obj
    return found


REPORT = {
    "rows": [row("osvp:nbv.pt", 3.0), row("oracle", -1.0), row("fixed:6", None)],
    "per_object": [row("osvp:nbv.pt", 5.0, "cow"), row("osvp:nbv.pt", -1.0, "spot"), row("oracle", -1.0, "cow")],
    "runs": [
        {"planner": "osvp:nbv.pt", "coverage_curve": [0.4, 0.7, 0.9]},
        {"planner": "osvp:nbv.pt", "coverage_curve": [0.2, 0.5]},
        {"planner": "oracle", "coverage_curve": [0.3]},
    ],
}


def test_the_table_names_planners_counts_objects_below_fixed_and_keeps_the_papers_rows(tables: ModuleType) -> None:
    lines = tables.table_lines(REPORT, {"osvp:nbv.pt": "NBVNet-style"}, 2)
    assert lines[2] == (
        "| NBVNet-style | 90.00 ± 1.00 | 6.00 ± 0.50 | 1.50 ± 0.10 | 3.00 ± 2.00 | - | 4.00 ± 1.00 | 1 |"
    )
    assert lines[3].startswith("| oracle |") and lines[3].endswith("| 1 |") and lines[4].endswith("| - |")
    assert "| PCNBV (NBV) | 96.58 ± 3.87 | 10 | 4.97 ± 0.49 |" in lines
    assert "| SCVP | 75.77 | 5.80 | - |" in tables.table_lines(REPORT, {}, 3)


def test_coverage_curves_average_runs_and_hold_a_stopped_run_at_its_last_value(tables: ModuleType) -> None:
    curves = tables.coverage_curves(REPORT)
    assert np.allclose(curves["osvp:nbv.pt"], [30.0, 60.0, 70.0]) and np.allclose(curves["oracle"], [30.0])


def test_the_planners_of_each_table(tables: ModuleType, tmp_path: Path) -> None:
    assert tables.planners_of(2, ["osvp:a.pt"], None) == ["osvp:a.pt", "oracle", "gain"]
    assert tables.planners_of(3, ["osvp:a.pt"], 6)[-3:] == ["fixed:6", "spread:6", "random:6"]
    tables.draw(REPORT, {}, tmp_path / "curves.png", "test")
    assert (tmp_path / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
