"""`random:match=SPEC`: chance at the matched planner's view count, situation by situation, and the lift it
gives that planner in the runs, the tables, the JSON and the budget figure's legend."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from typer.testing import CliRunner

from datagen.cli import common
from datagen.cli.main import app
from datagen.errors import PlannerError
from datagen.evaluate.baselines import MatchedRandomPlanner, match_planners
from datagen.evaluate.episode import Budget, Episode
from datagen.evaluate.figures import legend_label
from datagen.evaluate.planners import make_planner
from datagen.evaluate.protocol import Plan, Planner
from datagen.evaluate.report import markdown_table, per_object_rows, summarise
from datagen.evaluate.run import check_planners, run_situation
from datagen.evaluate.scored import ScoredPlanner
from datagen.evaluate.situation import LabelError, RefinedScene, Situation
from datagen.pipeline.random_streams import Purpose, stream

INITIAL_VIEWS = (0, 1, 2, 7, 13, 20, 31)


class StairScorer:
    """Scores 0.9 for 1 + initial % 3 views spread after the initial one, 0.1 elsewhere: a trained planner
    whose view count changes from situation to situation."""

    def view_probabilities(self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]) -> np.ndarray:
        initial = int(np.flatnonzero(view_state)[0])
        probabilities = np.full(view_state.size, 0.1)
        probabilities[[(initial + 1 + 5 * j) % view_state.size for j in range(1 + initial % 3)]] = 0.9
        return probabilities


class OddFails:
    """Fails (as the solver may) from every odd initial view; otherwise takes views 4 and 9."""

    name = "odd-fails"
    uses_refinement = True

    def plan(self, situation: Situation) -> Plan:
        if situation.initial_view % 2:
            raise LabelError("no proof of optimality in time")
        return Plan(views=(4, 9))


def expected_random(situation: Situation, count: int) -> tuple[int, ...]:
    """The views `count` uniform draws of this situation's evaluation stream give, initial view excluded."""
    scene, initial = situation.scene, situation.initial_view
    others = [v for v in range(scene.num_views) if v != initial]
    rng = stream(situation.config.seed, scene.object_id, scene.rotation, Purpose.EVALUATION, mask=1 << initial)
    return tuple(sorted(others[i] for i in rng.choice(len(others), size=count, replace=False)))


def untimed(episode: Episode) -> Episode:
    return dataclasses.replace(episode, planning_seconds=0.0)


def run_all(real: RefinedScene, planners: list[Planner], budget: Budget | None = None) -> dict[int, list[Episode]]:
    failures: list[str] = []
    runs = {v: run_situation(Situation(real, v), planners, budget or Budget(), failures) for v in INITIAL_VIEWS}
    assert failures == []
    return runs


# --- the view count ----------------------------------------------------------------------------------------


def test_matched_random_takes_the_matched_planners_count_in_every_situation(real: RefinedScene) -> None:
    net = ScoredPlanner("net", StairScorer())
    listed_first = match_planners([MatchedRandomPlanner("random:match=net", "net"), net])
    listed_last = match_planners([net, MatchedRandomPlanner("random:match=net", "net")])
    runs = run_all(real, listed_first)
    counts = []
    for initial, (chance, trained) in runs.items():
        assert (chance.planner, trained.planner) == ("random:match=net", "net")  # the order given
        count = 1 + initial % 3
        counts.append(count)
        assert len(trained.planned) == count and initial not in trained.planned
        assert chance.planned == expected_random(Situation(real, initial), count)
        assert chance.refiner == trained.refiner == "none"
        assert chance.visited[0] == trained.visited[0] == initial
        # The lift belongs to the planner's run: its coverage minus chance's, in percentage points.
        assert trained.matched_random_coverage == chance.coverage
        assert trained.lift == pytest.approx(100.0 * trained.coverage - 100.0 * chance.coverage, abs=1e-9)
        assert chance.matched_random_coverage is None and math.isnan(chance.lift)
    assert sorted(set(counts)) == [1, 2, 3]
    assert any(runs[v][1].lift != 0.0 for v in INITIAL_VIEWS)  # not a vacuous difference
    # Listing the random after its planner changes the output order, not the runs.
    for initial, episodes in run_all(real, listed_last).items():
        assert [untimed(e) for e in reversed(episodes)] == [untimed(e) for e in runs[initial]]


def test_the_plan_is_matched_before_the_budget_cuts_both(real: RefinedScene) -> None:
    net = ScoredPlanner("net", StairScorer())
    planners = match_planners([net, MatchedRandomPlanner("random:match=net", "net")])
    for initial, (trained, chance) in run_all(real, planners, Budget(views=2)).items():
        assert len(chance.planned) == len(trained.planned) == 1 + initial % 3
        assert trained.views == chance.views == 2  # both cut to two views, the initial one included


def test_random_match_oracle_gives_exactly_the_runs_of_random(real: RefinedScene) -> None:
    """Plain random already takes the oracle's view count from the same stream."""
    planners = check_planners(["random:match=oracle", "oracle", "random"])
    assert planners[0].uses_refinement is True
    for initial, (matched, oracle, plain) in run_all(real, planners).items():
        assert untimed(matched) == dataclasses.replace(untimed(plain), planner="random:match=oracle")
        assert len(matched.planned) == len(oracle.planned) > 0
        assert oracle.lift == pytest.approx(100.0 * (oracle.coverage - plain.coverage), abs=1e-9)
        assert plain.matched_random_coverage is None, initial


def test_a_failed_plan_skips_its_matched_random(real: RefinedScene) -> None:
    planners = match_planners([OddFails(), MatchedRandomPlanner("random:match=odd", "odd")])
    failures: list[str] = []
    for initial in (2, 3):
        episodes = run_situation(Situation(real, initial), planners, Budget(), failures)
        if initial == 2:
            assert [e.planner for e in episodes] == ["odd-fails", "random:match=odd"]
            assert episodes[1].planned == expected_random(Situation(real, 2), 2)
        else:
            assert episodes == []
    (line,) = failures
    assert line.startswith("capsule rotation 0 view 3 (none, odd-fails): ")


def test_a_matched_random_runs_under_its_planners_refiner_label(real: RefinedScene) -> None:
    (greedy, chance) = check_planners(["greedy:4", "random:match=greedy"])
    assert chance.uses_refinement is False
    trained_run, chance_run = run_situation(Situation(real, 5), [greedy, chance], Budget(), [])
    assert trained_run.refiner == chance_run.refiner == "-"
    assert chance_run.planned == expected_random(Situation(real, 5), 3)


# --- the spec ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("names", "matched"),
    [
        (["greedy:3", "oracle", "random:match=gre"], "greedy:3"),  # the prefix of one spec
        (["random:4", "random", "random:match=random"], "random"),  # an exact spec beats a longer one
        (["random:match=oracle", "oracle"], "oracle"),  # listed before its planner
    ],
)
def test_match_resolves(names: list[str], matched: str) -> None:
    (chance,) = [p for p in check_planners(names) if isinstance(p, MatchedRandomPlanner)]
    assert chance.matched == matched and chance.name in names


@pytest.mark.parametrize(
    ("names", "needle"),
    [
        (["oracle", "random:match=greedy"], "'greedy' names no other planner of this run; choose one of oracle"),
        (
            ["greedy:3", "greedy:5", "random:match=greedy"],
            "'greedy' is the start of 2 planners; give one in full; choose one of greedy:3, greedy:5",
        ),
        (
            ["oracle", "random:match=random"],
            "cannot match itself or another :match planner; choose one of oracle",
        ),
        (
            ["all", "random:match=all", "random:match=random:match=all"],
            "cannot match itself or another :match planner; choose one of all",
        ),
        (["random:match=oracle"], "names no other planner of this run; choose one of none: add the planner"),
    ],
)
def test_a_bad_match_is_one_planner_error(names: list[str], needle: str) -> None:
    with pytest.raises(PlannerError) as info:
        check_planners(names)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_match_names_a_planner() -> None:
    with pytest.raises(PlannerError, match="names no planner after '='"):
        make_planner("random:match=")


def test_an_unmatched_random_refuses_to_plan(real: RefinedScene) -> None:
    with pytest.raises(ValueError, match="view count"):
        MatchedRandomPlanner("random:match=net", "net").plan(Situation(real, 0))


# --- tables, JSON, legend ----------------------------------------------------------------------------------


def episode(
    object_id: str, planner: str, coverage: float, matched: float | None = None, refiner: str = "none"
) -> Episode:
    """A run that saw ``coverage`` of 1000 reference keys in one move."""
    return Episode(
        object_name=object_id,
        object_id=object_id,
        rotation=0,
        initial_view=0,
        refiner=refiner,
        planner=planner,
        planned=(1,),
        visited=(0, 1),
        step_metres=(0.5,),
        coverage_curve=(0.1, coverage),
        reference_size=1000,
        ground_truth_size=1000,
        observed_size=round(1000 * coverage),
        exact_path=True,
        planning_seconds=0.0,
        input_seconds=0.0,
        chamfer_mm=1.0,
        matched_random_coverage=matched,
    )


# Object a: lifts 20 and 10 points (mean 15); object b: one run, lift 5. Over objects: 10 ± 5.
RUNS = [
    episode("a", "net", 0.8, matched=0.6),
    episode("a", "random:match=net", 0.6),
    episode("a", "net", 0.7, matched=0.6),
    episode("a", "random:match=net", 0.6),
    episode("b", "net", 0.5, matched=0.45),
    episode("b", "random:match=net", 0.45),
]


def test_lift_is_averaged_over_runs_then_objects() -> None:
    net, chance = summarise(RUNS)
    assert (net.planner, chance.planner) == ("net", "random:match=net")
    assert net.mean["lift"] == pytest.approx(10.0) and net.std["lift"] == pytest.approx(5.0)
    assert math.isnan(chance.mean["lift"])
    assert net.as_dict()["lift"] == pytest.approx(10.0) and net.as_dict()["lift_std"] == pytest.approx(5.0)
    assert chance.as_dict()["lift"] is None
    object_a = per_object_rows(RUNS)[0]
    assert (object_a.object_name, object_a.planner) == ("a", "net")
    assert object_a.mean["lift"] == pytest.approx(15.0) and object_a.std["lift"] == pytest.approx(5.0)


def test_tables_show_lift_only_when_a_row_has_one() -> None:
    head, _, net, chance = markdown_table(summarise(RUNS)).splitlines()
    columns = [c.strip() for c in head.strip("|").split("|")]
    assert columns[:4] == ["refiner", "planner", "coverage %", "lift vs random %"]
    assert [c.strip() for c in net.strip("|").split("|")][3] == "10.00 ± 5.00"
    assert [c.strip() for c in chance.strip("|").split("|")][3] == "-"
    per_object = markdown_table(per_object_rows(RUNS)).splitlines()
    assert "| lift vs random % |" in per_object[0] and per_object[2].startswith(
        "| a | none | net | 75.00 ± 5.00 | 15.00 ± 5.00 |"
    )
    assert "lift" not in markdown_table(summarise([episode("a", "oracle", 0.9)]))


def test_a_run_as_json_carries_its_lift() -> None:
    trained, chance = RUNS[0].as_dict(), RUNS[1].as_dict()
    assert trained["lift"] == pytest.approx(20.0) and trained["matched_random_coverage"] == pytest.approx(60.0)
    assert chance["lift"] is None and chance["matched_random_coverage"] is None
    json.dumps([trained, chance])  # plain data


def test_the_legend_names_the_lift() -> None:
    assert legend_label([e for e in RUNS if e.planner == "net"]) == "net (none) (+10.0 vs random at equal views)"
    assert legend_label([e for e in RUNS if e.planner != "net"]) == "random:match=net (none)"
    below = [episode("a", "net", 0.5, matched=0.6)]
    assert legend_label(below) == "net (none) (-10.0 vs random at equal views)"


def test_the_command_reports_lift(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(common.console, "_width", 400)
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    config = tmp_path / "config.toml"
    config.write_text('refiner = "none"\n')
    args = ["evaluate", "--workers", "1", "--objects", str(objects), "--config", str(config), "--initial-views", "0,5"]
    args += ["-p", "random:match=oracle", "-p", "oracle", "-p", "greedy:3"]
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    chance, oracle, greedy = report["rows"]
    assert [row["planner"] for row in report["rows"]] == ["random:match=oracle", "oracle", "greedy:3"]
    assert chance["lift"] is None  # a baseline has no lift over a baseline
    # every planner that looks at the object is compared with random views at its own count, run by run
    assert greedy["lift"] is not None and all(
        r["matched_random_coverage"] is not None for r in report["runs"] if r["planner"] == "greedy:3"
    )
    runs = {(r["planner"], r["initial_view"]): r for r in report["runs"]}
    lifts = [runs["oracle", v]["coverage"] - runs["random:match=oracle", v]["coverage"] for v in (0, 5)]
    for view, lift in zip((0, 5), lifts, strict=True):
        assert runs["oracle", view]["lift"] == pytest.approx(lift, abs=1e-5)
        assert runs["oracle", view]["matched_random_coverage"] == runs["random:match=oracle", view]["coverage"]
    assert oracle["lift"] == pytest.approx(sum(lifts) / 2, abs=1e-5) and oracle["lift"] > 0
    table = CliRunner().invoke(app, args).stdout.splitlines()
    assert table[0].startswith("| refiner | planner | coverage % | lift vs random % |")
    assert table[2].startswith("| none | random:match=oracle |") and table[2].split("|")[4].strip() == "-"
    assert table[3].split("|")[4].strip() == f"{oracle['lift']:.2f} ± {oracle['lift_std']:.2f}"
