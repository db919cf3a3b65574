"""`datagen evaluate --margins` (datagen/evaluate/margins.py) on a toy evaluation whose numbers are
worked out by hand: the floor is the better of fixed and spread in each situation, the ceiling is the
true gains played step by step, and a planner's captured share is its mean margin over the ceiling's;
views to a share read from a hand-made curve."""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.errors import InvalidArgument
from datagen.evaluate.episode import Episode
from datagen.evaluate.margins import coverage_at, margin_rows, margin_table, views_to_share


def run(planner: str, obj: str, initial: int, *, counts=None, curve=(), ordered=False, refiner="-") -> Episode:
    """A run with only what the margins read: its coverage at every count or along its own order."""
    return Episode(
        object_name=obj, object_id=obj, rotation=0, initial_view=initial, refiner=refiner, planner=planner,
        planned=(), visited=tuple(range(len(curve))), step_metres=(), coverage_curve=tuple(curve),
        reference_size=100, ground_truth_size=100, observed_size=0, exact_path=True, planning_seconds=0.0,
        input_seconds=0.0, chamfer_mm=math.nan, count_curve=None if counts is None else tuple(counts), ordered=ordered,
    )  # fmt: skip


def toy() -> list[Episode]:
    """Object "a" in two situations (initial views 0 and 8), object "b" in one; coverage at 1, 2, 3 views."""
    return [
        # a, initial view 0: fixed 0.50/0.70/0.80, spread 0.50/0.72/0.78 -> floor at 3 views: 0.80
        run("fixed", "a", 0, counts=(0.50, 0.70, 0.80)),
        run("spread", "a", 0, counts=(0.50, 0.72, 0.78)),
        run("gain", "a", 0, curve=(0.50, 0.80, 0.90), ordered=True),
        run("osvp:m.pt", "a", 0, counts=(0.50, 0.75, 0.85), refiner="poco"),
        # a, initial view 8: floor at 3 views 0.60 (spread), ceiling 0.70, planner 0.60
        run("fixed", "a", 8, counts=(0.40, 0.50, 0.55)),
        run("spread", "a", 8, counts=(0.40, 0.52, 0.60)),
        run("gain", "a", 8, curve=(0.40, 0.60, 0.70), ordered=True),
        run("osvp:m.pt", "a", 8, counts=(0.40, 0.50, 0.60), refiner="poco"),
        # b: floor 0.90, ceiling 0.94, planner 0.88 (below the floor)
        run("fixed", "b", 0, counts=(0.60, 0.85, 0.90)),
        run("gain", "b", 0, curve=(0.60, 0.90, 0.94), ordered=True),
        run("osvp:m.pt", "b", 0, counts=(0.60, 0.80, 0.88), refiner="poco"),
    ]


def test_coverage_at_a_budget_and_views_to_a_share_by_hand() -> None:
    one_shot = run("osvp", "a", 0, counts=(0.5, 0.9, 0.96, 0.995))
    played = run("gain", "a", 0, curve=(0.5, 0.95, 0.99), ordered=True)
    route = run("oracle", "a", 0, curve=(0.5, 0.95, 0.99))  # a set in route order: no answer per count
    assert coverage_at(one_shot, 3) == 0.96 and coverage_at(played, 2) == 0.95
    assert math.isnan(coverage_at(route, 2)) and math.isnan(coverage_at(played, 4))
    finished = run("gain", "a", 0, curve=(0.5, 0.95, 1.0), ordered=True)  # stopped: it has seen everything
    assert coverage_at(finished, 6) == 1.0
    assert views_to_share(one_shot, 0.95) == 3.0 and views_to_share(one_shot, 0.99) == 4.0
    assert views_to_share(played, 0.95) == 2.0 and views_to_share(played, 0.99) == 3.0
    assert math.isnan(views_to_share(route, 0.95)) and math.isnan(views_to_share(one_shot, 0.999))


def test_captured_share_against_a_hand_computation() -> None:
    rows_of = margin_rows(toy(), [3])
    assert [(r.object_name, r.planner) for r in rows_of if r.planner == "gain"] == [
        ("a", "gain"),
        ("b", "gain"),
        ("all", "gain"),
    ]
    ceiling = next(r for r in rows_of if r.planner == "gain" and r.object_name == "a")
    assert ceiling.margin == ceiling.ceiling_margin == pytest.approx(10.0) and ceiling.captured == 1.0
    rows = {(r.object_name, r.views): r for r in rows_of if r.planner == "osvp:m.pt@poco"}
    a, b, every = rows[("a", 3)], rows[("b", 3)], rows[("all", 3)]
    # a: planner (0.85 + 0.60) / 2 = 72.5 %; floor (0.80 + 0.60) / 2 = 70 %; ceiling (0.90 + 0.70) / 2 = 80 %
    assert (a.runs, a.coverage, a.floor, a.ceiling) == (
        2,
        pytest.approx(72.5),
        pytest.approx(70.0),
        pytest.approx(80.0),
    )
    assert a.margin == pytest.approx(2.5) and a.ceiling_margin == pytest.approx(10.0)
    assert a.captured == pytest.approx(0.25)
    # b: margin 88 - 90 = -2, room 94 - 90 = 4: -50 %
    assert b.margin == pytest.approx(-2.0) and b.captured == pytest.approx(-0.5)
    # over objects: mean margin (2.5 - 2) / 2 = 0.25 of mean room (10 + 4) / 2 = 7
    assert every.margin == pytest.approx(0.25) and every.captured == pytest.approx(0.25 / 7.0)
    assert every.runs == 3
    table = margin_table(list(rows.values()))
    assert "| a | osvp:m.pt@poco | 3 | 2 | 72.50 | 70.00 | 80.00 | 2.50 | 10.00 | 25% |" in table


def test_margins_need_the_ceiling_and_a_floor() -> None:
    without_gain = [e for e in toy() if e.planner != "gain"]
    with pytest.raises(InvalidArgument, match="add -p gain"):
        margin_rows(without_gain, [3])


def test_the_cli_refuses_bad_margins_before_any_work(tmp_path) -> None:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    for args, needle in (
        (["-p", "osvp:x.pt", "--margins", "3"], "needs the ceiling and a floor"),
        (["-p", "gain", "-p", "spread", "--margins", "three"], "give view counts separated by commas"),
        (["-p", "gain", "-p", "spread", "--margins", "1,40"], "give view counts from 2 to 32"),
    ):
        result = CliRunner().invoke(app, ["evaluate", "--objects", str(objects), *args])
        assert result.exit_code == 2, result.output
        assert needle in result.stderr and result.stdout == ""


def test_views_to_a_share_say_how_many_runs_ever_reach_it() -> None:
    """Issue 52, finding 8: "views to 0.99 = 3" over the runs that reach 99 % must not read like every
    run did; where some never do, the cell says how many do."""
    from datagen.evaluate.margins import MARGIN_COLUMNS, margin_cells

    rows = {(r.object_name, r.planner, r.views): r for r in margin_rows(toy(), [3])}
    planner = rows[("a", "osvp:m.pt@poco", 3)]
    assert planner.reached == {0.95: 0, 0.99: 0}
    gain = rows[("all", "gain", 3)]
    cells = dict(zip(MARGIN_COLUMNS, margin_cells([gain])[0], strict=True))
    assert cells["runs"] == "3" and cells["views to 0.95"] == "- (0/3)"
    assert gain.as_dict()["reached_0.95"] == 0


def test_the_cli_prints_a_legend_above_the_margins(tmp_path) -> None:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    result = CliRunner().invoke(
        app, ["evaluate", "--objects", str(objects), "-p", "gain", "-p", "spread", "--margins", "2", "--workers", "1"]
    )
    assert result.exit_code == 0, result.output
    for word in ("floor:", "ceiling:", "margin:", "captured:", "views to 0.95 / 0.99:"):
        assert any(line.strip().startswith(word) for line in result.output.splitlines()), word
