"""Next-best-view play (`datagen.evaluate.sequential`): the true-gain scorer reproduces ``greedy`` view for
view, a scorer sees what the views taken observed (cloud, view state, occupancy grid in visiting order),
a scorer that fails mid-episode is one error line naming the planner and the step, and budgets hold."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from datagen.errors import PlannerError
from datagen.evaluate.episode import Budget, run_episode
from datagen.evaluate.planners import GreedyPlanner, make_planner
from datagen.evaluate.protocol import PlannerContext
from datagen.evaluate.sequential import DEFAULT_TOTAL_VIEWS, SequentialPlanner, TrueGains
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.occupancy import view_grids
from schemas.planning import NextViewObservation, NextViewScorer
from storage.samples import case_grid, pack_cells

INITIALS = (0, 9, 17, 31)


@pytest.mark.parametrize("total", [None, 2, 5, 10, 32])
def test_true_gains_play_greedy_view_for_view(real: RefinedScene, total: int | None) -> None:
    for initial in INITIALS:
        situation = Situation(real, initial)
        played = make_planner("gain" if total is None else f"gain:{total}").plan(situation)
        greedy = GreedyPlanner(total).plan(situation)
        if total is None:  # greedy stops when nothing is left; play also stops after 10 views in all
            assert played.views == greedy.views[: DEFAULT_TOTAL_VIEWS - 1]
        else:
            assert played.views == greedy.views
        assert played.ordered


def test_a_view_budget_sets_how_many_views_are_played(real: RefinedScene) -> None:
    situation = Situation(real, 4)
    planner = make_planner("gain", PlannerContext(budget_views=6))
    assert len(planner.plan(situation).views) == 5
    episode = run_episode(planner, situation, Budget(views=6))
    assert episode.visited == (4, *GreedyPlanner(6).plan(situation).views)
    assert len(episode.coverage_curve) == 6 and list(episode.coverage_curve) == sorted(episode.coverage_curve)
    cut = run_episode(make_planner("gain:8"), situation, Budget(views=3))
    assert len(cut.visited) == 3


class Recorder:
    """Scores view v by -v (the lowest open index wins), remembering every observation."""

    def __init__(self) -> None:
        self.seen: list[NextViewObservation] = []

    def next_view_scores(self, observation: NextViewObservation) -> npt.NDArray[np.float64]:
        self.seen.append(observation)
        return 100.0 - np.arange(observation.view_state.size, dtype=np.float64)


def test_a_scorer_sees_the_cloud_state_and_grid_of_the_views_taken(real: RefinedScene) -> None:
    recorder = Recorder()
    assert isinstance(recorder, NextViewScorer)
    situation = Situation(real, 5)
    plan = SequentialPlanner("rec", lambda s: recorder, 4).plan(situation)
    assert plan.views == (0, 1, 2)
    scene = real.scene
    config = real.config
    walked = view_grids(
        [o.keys for o in scene.scan.observations],
        scene.scan.ground_truth.keys,
        scene.positions,
        config.voxel_size,
        config.grid_offset,
    )
    assert [o.views for o in recorder.seen] == [(5,), (5, 0), (5, 0, 1)]
    for observation in recorder.seen:
        taken = list(observation.views)
        assert observation.view_state.tolist() == [float(v in taken) for v in range(scene.num_views)]
        np.testing.assert_array_equal(observation.cloud, scene.observed_points(taken))
        # inserted in visiting order; this scorer's order (5, 0, 1) differs from ascending (0, 1, 5)
        order = np.array(taken)
        hits, misses = walked.hits[order], walked.misses[order]
        expected = case_grid(hits, misses, (1 << len(taken)) - 1)
        np.testing.assert_array_equal(observation.grid, expected)
    assert pack_cells(np.zeros(8 * 4096, dtype=bool)).shape == (4096,)


class Failing:
    def __init__(self, after: int) -> None:
        self.calls, self.after = 0, after

    def next_view_scores(self, observation: NextViewObservation) -> npt.NDArray[np.float64]:
        self.calls += 1
        if self.calls > self.after:
            raise RuntimeError("CUDA out of memory\nTraceback details")
        return np.ones(observation.view_state.size)


def test_a_scorer_failing_mid_episode_is_one_line_naming_the_planner_and_step(real: RefinedScene) -> None:
    planner = SequentialPlanner("nbv:ckpt.pt", lambda s: Failing(after=2), 8)
    with pytest.raises(PlannerError) as raised:
        planner.plan(Situation(real, 3))
    message = str(raised.value)
    assert message == "planner nbv:ckpt.pt failed at step 3 (after views 3, 0, 1): RuntimeError: CUDA out of memory"


@pytest.mark.parametrize("scores", [np.ones(5), np.full(32, np.nan)])
def test_scores_of_the_wrong_shape_or_not_finite_are_one_line(real: RefinedScene, scores: np.ndarray) -> None:
    class Bad:
        def next_view_scores(self, observation: NextViewObservation) -> np.ndarray:
            return scores

    with pytest.raises(PlannerError, match=r"^planner bad returned \(\d+,\) scores at step 1 for 32 views"):
        SequentialPlanner("bad", lambda s: Bad(), 4).plan(Situation(real, 0))


def test_nothing_left_stops_play_unless_a_count_was_asked(real: RefinedScene) -> None:
    class Done:
        uses_grid = False

        def next_view_scores(self, observation: NextViewObservation) -> np.ndarray:
            return np.zeros(observation.view_state.size)

    situation = Situation(real, 2)
    assert SequentialPlanner("done", lambda s: Done()).plan(situation).views == ()
    assert SequentialPlanner("done", lambda s: Done(), 4).plan(situation).views == (0, 1, 3)


def test_true_gains_count_what_the_views_taken_miss(real: RefinedScene) -> None:
    scene = real.scene
    gains = TrueGains(scene)
    observation = NextViewObservation(
        views=(7,), view_state=np.zeros(32, np.float32), cloud=np.zeros((0, 3), np.float32), grid=None
    )
    seen = set(scene.reference[scene.view_columns[7]].tolist())
    expected = [len(set(scene.reference[c].tolist()) - seen) for c in scene.view_columns]
    assert gains.next_view_scores(observation).tolist() == expected
