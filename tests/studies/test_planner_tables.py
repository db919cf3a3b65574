"""studies/planners/tables.py on a made-up `datagen evaluate --json` report, and its reading of a
budget against a real budgeted evaluation (the evaluation itself is measured by hand:
osvp/recipe/RESULTS.md)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def tables() -> ModuleType:
    return load_study("planners.tables")


def row(planner: str, lift_fixed: float | None, obj: str | None = None) -> dict[str, Any]:
    found: dict[str, Any] = {"planner": planner, "coverage": 90.0, "coverage_std": 1.0, "views": 6.0}
    found.update(views_std=0.5, movement=1.5, movement_std=0.1, lift=4.0, lift_std=1.0, lift_spread=None)
    found.update(lift_fixed=lift_fixed, lift_fixed_std=None if lift_fixed is None else 2.0)
    if obj is not None:
        found["object"] = obj
    return found


def run(planner: str, obj: str, curve: list[float], steps: list[float] | None = None) -> dict[str, Any]:
    steps = [0.5] * (len(curve) - 1) if steps is None else steps
    return {"planner": planner, "object_name": obj, "rotation": 0, "initial_view": 0, "coverage_curve": curve} | {
        "step_metres": steps
    }


REPORT = {
    "rows": [row("osvp:nbv.pt", 3.0), row("oracle", -1.0), row("fixed:2", None), row("random:2", None)],
    "per_object": [row("osvp:nbv.pt", 5.0, "cow"), row("osvp:nbv.pt", -1.0, "spot"), row("oracle", -1.0, "cow")],
    "runs": [
        run("osvp:nbv.pt", "cow", [0.4, 0.7, 0.9]),
        run("osvp:nbv.pt", "spot", [0.2, 0.5]),
        run("oracle", "cow", [0.3]),
        run("fixed:2", "cow", [0.3, 0.6]),
        run("fixed:2", "spot", [0.1, 0.55]),
        run("random:2", "cow", [0.3, 0.4]),
    ],
}


def test_table_two_names_planners_counts_objects_below_fixed_and_keeps_the_papers_rows(tables: ModuleType) -> None:
    lines = tables.table_two(REPORT, {"osvp:nbv.pt": "NBVNet-style"})
    assert lines[2] == (
        "| NBVNet-style | 90.00 ± 1.00 | 6.00 ± 0.50 | 1.50 ± 0.10 | 3.00 ± 2.00 | - | 4.00 ± 1.00 | 1 |"
    )
    assert lines[3].startswith("| oracle |") and not any(line.startswith("| fixed:2") for line in lines)
    assert "| PCNBV (NBV) | 96.58 ± 3.87 | 10 | 4.97 ± 0.49 |" in lines


def test_table_three_holds_every_run_to_the_budget_against_the_floors_in_the_same_situation(
    tables: ModuleType,
) -> None:
    found = tables.budget_rows(REPORT, 2)["osvp:nbv.pt"]
    assert np.allclose(found["coverage"], [70.0, 50.0]) and np.allclose(found["views"], [2.0, 2.0])
    assert np.allclose(found["lift_fixed"], [10.0, -5.0]) and np.allclose(found["lift_random"], [30.0])
    assert np.allclose(found["movement"], [0.5, 0.5])
    lines = tables.table_three(REPORT, {}, 2)
    assert lines[2] == "| osvp:nbv.pt | 60.00 ± 10.00 | 2.00 ± 0.00 | 0.50 ± 0.00 | 2.50 ± 7.50 | 30.00 ± 0.00 | 1 |"
    assert "| SCVP | 75.77 | 5.80 | - |" in lines
    assert tables.lift_by_budget(REPORT, {})[2].startswith("| osvp:nbv.pt | +2.50 |")


def test_curves_planners_and_picture(tables: ModuleType, tmp_path: Path) -> None:
    curves = tables.coverage_curves(REPORT)
    assert np.allclose(curves["osvp:nbv.pt"], [30.0, 60.0, 70.0]) and "fixed:2" not in curves
    planners = tables.planners_of(["osvp:a.pt"])
    assert planners[:3] == ["osvp:a.pt", "oracle", "gain"] and planners[-1] == "random:10" and len(planners) == 21
    tables.draw(REPORT, {}, tmp_path / "curves.png", "test")
    assert (tmp_path / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_budget_read_from_a_run_is_what_a_budgeted_evaluation_reports(tables: ModuleType, tmp_path: Path) -> None:
    """`datagen evaluate --budget-views K` keeps the first K views of the visiting order: the coverage and
    movement the benchmark reads from an unbudgeted run equal a budgeted run's, for a next-best-view
    planner and a one-shot plan."""
    from support.storage import config

    from datagen.evaluate.episode import Budget, run_episode
    from datagen.evaluate.planners import make_planner
    from datagen.evaluate.scene import build_scene
    from datagen.evaluate.situation import RefinedScene, Situation
    from datagen.pipeline.objects.objects_file import read_objects_file
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.refine.factory import make_refiner
    from datagen.pipeline.viewspace import build_view_space

    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    cfg = config()
    prepared = prepare_object(read_objects_file(objects).objects[0], cfg)
    scene = build_scene(prepared, 0, cfg, build_view_space(cfg.view_space))
    situation = Situation(RefinedScene(scene, make_refiner(cfg), cfg), 3)
    for spec in ("gain", "spread:8"):
        whole = run_episode(make_planner(spec), situation).as_dict()
        for views in (2, 5):
            held = run_episode(make_planner(spec), situation, Budget(views=views))
            coverage, kept, moved = tables.at_budget(whole, views)
            assert (coverage, kept) == (pytest.approx(100.0 * held.coverage), len(held.visited)), (spec, views)
            assert moved == pytest.approx(held.movement, abs=1e-5), (spec, views)
