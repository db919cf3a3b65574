"""Simulated runs (`datagen.evaluate.episode`) on hand-built scenes whose figures are computed by hand, the
open-path heuristic against Held-Karp, and `visit_order`'s exact/heuristic switch."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from datagen.errors import InvalidArgument
from datagen.evaluate import path as path_module
from datagen.evaluate.baselines import AllPlanner
from datagen.evaluate.episode import Budget, Episode, chamfer_mm, run_episode
from datagen.evaluate.oracle import OraclePlanner
from datagen.evaluate.path import held_karp, open_path_heuristic, order_views, path_matrix, visit_order
from datagen.evaluate.protocol import Plan
from datagen.evaluate.scene import Scene, build_scene
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.ground_truth import GroundTruth
from datagen.pipeline.imaging import Observation, TaskImaging
from datagen.pipeline.objects.prepare import PreparedObject, prepare_object
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

# The hand-built scene: six views on a circle of radius R in the z = 0 plane, 60 degrees apart, around an
# obstacle of radius r. A 60-degree chord passes R cos 30° = 0.346 m from the centre and a 120-degree chord
# R cos 60° = 0.2 m, both outside r = 0.1 m, so those moves are straight chords 2R sin(θ/2); opposite views
# (180 degrees) go round the obstacle: 2(R - r) + π r.
R = 0.4
OBSTACLE = 0.1
CHORD_60 = 2 * R * math.sin(math.radians(30))  # 0.4
CHORD_120 = 2 * R * math.sin(math.radians(60))  # 0.4·sqrt(3)
DETOUR_180 = 2 * (R - OBSTACLE) + math.pi * OBSTACLE

REFERENCE = np.array([2, 3, 5, 7, 11, 13, 17, 19, 23, 29], dtype=np.int64)
EXTRA_GT_KEYS = np.array([31, 37], dtype=np.int64)
"""Keys of P_gt no view sees: coverage_gt divides by 12, coverage by 10."""
COLUMNS = ([0, 1, 2], [2, 3], [3, 4, 5, 6], [6, 7], [7, 8, 9], [0, 9])
"""Which reference indices each view sees."""


def hand_scene(spec: ObjectSpec) -> Scene:
    """Ground-truth point i lies at x = i mm, so Chamfer distances are whole millimetre counts."""
    gt_keys = np.concatenate([REFERENCE, EXTRA_GT_KEYS])
    gt_points = np.zeros((gt_keys.size, 3))
    gt_points[:, 0] = 0.001 * np.arange(gt_keys.size)
    angles = np.radians(60.0 * np.arange(6))
    positions = np.stack([R * np.cos(angles), R * np.sin(angles), np.zeros(6)], axis=1)
    observations = tuple(
        Observation(
            views=(v,),
            origins=positions[v : v + 1],
            points=gt_points[cols].astype(np.float32),
            point_views=np.full(len(cols), v, dtype=np.uint8),
            pixels=np.zeros((len(cols), 2), dtype=np.float32),
            keys=REFERENCE[cols],
        )
        for v, cols in enumerate(COLUMNS)
    )
    scan = TaskImaging(
        observations=observations,
        ground_truth=GroundTruth(keys=gt_keys, points=gt_points, sampled=gt_keys.size),
        rays_cast=0,
        seconds=0.0,
    )
    prepared = PreparedObject(
        spec=spec,
        vertices=np.zeros((1, 3)),
        faces=np.zeros((0, 3), dtype=np.int64),
        units_guessed="m",
        scale=1.0,
        size=0.1,
        watertight=True,
    )
    return Scene(
        prepared=prepared,
        rotation=2,
        scan=scan,
        positions=positions,
        obstacle_radius=OBSTACLE,
        reference=REFERENCE.copy(),
        view_columns=tuple(np.asarray(c, dtype=np.int64) for c in COLUMNS),
    )


@pytest.fixture(scope="module")
def refined_hand(spec: ObjectSpec, config: GenerationConfig) -> RefinedScene:
    return RefinedScene(hand_scene(spec), make_refiner(config), config)


class FixedPlanner:
    """Returns the plan it was given."""

    uses_refinement = False

    def __init__(self, views: tuple[int, ...], ordered: bool, name: str = "fixed") -> None:
        self.name = name
        self.result = Plan(views=views, ordered=ordered)

    def plan(self, situation: Situation) -> Plan:
        return self.result


def _run(
    refined: RefinedScene, initial: int, views: tuple[int, ...], ordered: bool, budget: Budget | None = None
) -> Episode:
    return run_episode(FixedPlanner(views, ordered), Situation(refined, initial), budget or Budget())


# --- figures of one run ----------------------------------------------------------------------------------


def test_figures_on_hand_scene(refined_hand: RefinedScene, spec: ObjectSpec) -> None:
    """0 → 1 → 3: keys {0,1,2} ∪ {2,3} ∪ {6,7} = 6 of 10 reference keys (6 of 12 of P_gt); one 60-degree and
    one 120-degree chord."""
    episode = _run(refined_hand, 0, (1, 3), ordered=True)
    assert episode.visited == (0, 1, 3)
    assert episode.planned == (1, 3)
    assert episode.step_metres == pytest.approx((CHORD_60, CHORD_120), rel=1e-12)
    assert math.isclose(CHORD_60, 0.4) and math.isclose(CHORD_120, 0.4 * math.sqrt(3))
    assert episode.coverage_curve == pytest.approx((0.3, 0.4, 0.6), rel=1e-15)
    assert (episode.reference_size, episode.ground_truth_size, episode.observed_size) == (10, 12, 6)
    assert episode.coverage == pytest.approx(0.6, rel=1e-15)
    assert episode.coverage_gt == pytest.approx(0.5, rel=1e-15)
    assert episode.views == 3
    movement = 0.4 + 0.4 * math.sqrt(3)
    assert episode.movement == pytest.approx(movement, rel=1e-12)
    assert episode.coverage_per_view == pytest.approx(20.0, rel=1e-12)
    assert episode.coverage_per_metre == pytest.approx(60.0 / movement, rel=1e-12)
    # Observed x = {0,1,2,3,6,7} mm; distances from the 12 truth points 0..11 mm: 0,0,0,0,1,1,0,0,1,2,3,4 → mean 1;
    # the observed points are truth points, so the forward term is 0 and the Chamfer mean is 0.5 mm.
    assert episode.chamfer_mm == pytest.approx(0.5, abs=1e-6)
    assert episode.exact_path is True
    assert (episode.object_name, episode.object_id) == (spec.name, spec.object_id)
    # A planner that reads neither the refined input nor the label has no refiner and no input time.
    assert (episode.rotation, episode.initial_view, episode.refiner, episode.planner) == (2, 0, "-", "fixed")
    assert episode.planning_seconds >= 0.0 and episode.input_seconds == 0.0
    figures = episode.figures()
    assert figures["coverage"] == pytest.approx(60.0)
    assert figures["coverage_gt"] == pytest.approx(50.0)
    assert figures["views"] == 3.0
    assert figures["movement"] == pytest.approx(movement)
    assert figures["coverage_per_view"] == pytest.approx(20.0)
    assert figures["coverage_per_metre"] == pytest.approx(60.0 / movement)
    assert figures["chamfer_mm"] == pytest.approx(0.5, abs=1e-6)
    assert figures["input_seconds"] == 0.0


def test_opposite_views_go_round_the_obstacle(refined_hand: RefinedScene) -> None:
    """0 → 3 → 5: the first move crosses the centre (half circle of the obstacle), the second is a 120° chord."""
    episode = _run(refined_hand, 0, (3, 5), ordered=True)
    assert episode.step_metres == pytest.approx((DETOUR_180, CHORD_120), rel=1e-12)
    assert math.isclose(DETOUR_180, 0.6 + 0.1 * math.pi)
    # {0,1,2} ∪ {6,7} ∪ {0,9} = 6 keys.
    assert episode.coverage_curve == pytest.approx((0.3, 0.5, 0.6))
    assert episode.coverage_per_metre == pytest.approx(60.0 / (DETOUR_180 + CHORD_120), rel=1e-12)


def test_every_view_covers_the_reference(refined_hand: RefinedScene) -> None:
    episode = run_episode(AllPlanner(), Situation(refined_hand, 0))
    assert episode.planner == "all"
    assert sorted(episode.visited) == list(range(6)) and episode.visited[0] == 0
    # Around the hexagon one way or the other: five 60-degree chords.
    assert episode.visited in ((0, 1, 2, 3, 4, 5), (0, 5, 4, 3, 2, 1))
    assert episode.movement == pytest.approx(5 * CHORD_60, rel=1e-12)
    assert episode.coverage == 1.0 and episode.coverage_curve[-1] == 1.0
    assert episode.coverage_per_view == pytest.approx(100.0 / 6)
    # Every reference point observed: backward distances 0 for 0..9 mm, 1 and 2 for the unseen 10 and 11 mm.
    assert episode.chamfer_mm == pytest.approx(3.0 / 12 / 2, abs=1e-6)


def test_only_the_initial_view(refined_hand: RefinedScene) -> None:
    episode = _run(refined_hand, 4, (), ordered=False)
    assert episode.visited == (4,) and episode.step_metres == ()
    assert episode.coverage == pytest.approx(0.3) and episode.views == 1 and episode.movement == 0.0
    assert episode.coverage_per_view == pytest.approx(30.0)
    assert math.isnan(episode.coverage_per_metre)
    assert episode.as_dict()["coverage_per_metre"] is None  # NaN is not JSON


# --- visiting order ----------------------------------------------------------------------------------------


def test_one_shot_set_is_visited_along_the_shortest_open_path(refined_hand: RefinedScene) -> None:
    # From 0, {5, 4}: 0 → 5 → 4 costs two 60° chords, 0 → 4 → 5 a 120° chord and a 60° one.
    episode = _run(refined_hand, 0, (4, 5), ordered=False)
    assert episode.visited == (0, 5, 4)
    assert episode.planned == (4, 5)
    assert episode.movement == pytest.approx(2 * CHORD_60, rel=1e-12)
    assert episode.exact_path is True
    # From 0, {3, 1, 2}: straight round the circle, three 60° chords; any other order is longer.
    episode = _run(refined_hand, 0, (3, 1, 2), ordered=False)
    assert episode.visited == (0, 1, 2, 3)
    assert episode.step_metres == pytest.approx((CHORD_60,) * 3, rel=1e-12)


def test_one_shot_order_matches_brute_force(refined_hand: RefinedScene) -> None:
    scene = refined_hand.scene
    for initial in range(6):
        for size in range(1, 6):
            for planned in itertools.combinations([v for v in range(6) if v != initial], size):
                episode = _run(refined_hand, initial, planned[::-1], ordered=False)
                best = min(
                    sum(
                        float(path_matrix(scene.positions[[a, b]], np.zeros(3), OBSTACLE)[0, 1])
                        for a, b in itertools.pairwise((initial, *perm))
                    )
                    for perm in itertools.permutations(planned)
                )
                assert episode.movement == pytest.approx(best, rel=1e-9)
                assert episode.visited[0] == initial and sorted(episode.visited[1:]) == list(planned)


def test_ordered_plan_is_visited_as_given(refined_hand: RefinedScene) -> None:
    """Duplicates and the initial view are dropped; the rest keeps the planner's order (not the shortest)."""
    episode = _run(refined_hand, 1, (4, 1, 0, 4, 2, 0), ordered=True)
    assert episode.visited == (1, 4, 0, 2)
    assert episode.step_metres == pytest.approx((DETOUR_180, CHORD_120, CHORD_120), rel=1e-12)
    # One-shot with the same views: duplicates and the initial view dropped, then the shortest open path.
    one_shot = _run(refined_hand, 1, (4, 1, 0, 4, 2, 0), ordered=False)
    order, cost = order_views(1, [4, 1, 0, 4, 2, 0], refined_hand.scene.positions, np.zeros(3), OBSTACLE)
    assert one_shot.visited == tuple(order) and sorted(order) == [0, 1, 2, 4]
    assert one_shot.movement == pytest.approx(cost, rel=1e-12)
    assert one_shot.movement < episode.movement


@pytest.mark.parametrize("ordered", [False, True])
@pytest.mark.parametrize("bad", [6, -1])
def test_view_outside_the_scene_raises(refined_hand: RefinedScene, ordered: bool, bad: int) -> None:
    with pytest.raises(InvalidArgument, match=r"outside 0\.\.5"):
        _run(refined_hand, 0, (1, bad), ordered=ordered)


# --- budgets -----------------------------------------------------------------------------------------------

PATH = (1, 3, 4, 5)
"""0 → 1 → 3 → 4 → 5: moves 60°, 120°, 60°, 60°."""
STEPS = (CHORD_60, CHORD_120, CHORD_60, CHORD_60)
CURVE = (0.3, 0.4, 0.6, 0.8, 0.8)
"""{0,1,2}; +{3}; +{6,7}; +{8,9}; +{} (view 5's keys 0 and 9 are already seen)."""


@pytest.mark.parametrize(
    ("budget", "kept"),
    [
        (Budget(), 5),
        (Budget(views=1), 1),
        (Budget(views=3), 3),
        (Budget(views=5), 5),
        (Budget(views=50), 5),
        (Budget(metres=0.39), 1),
        (Budget(metres=CHORD_60), 2),
        (Budget(metres=1.0), 2),
        (Budget(metres=CHORD_60 + CHORD_120), 3),
        (Budget(metres=1.5), 4),
        (Budget(metres=100.0), 5),
        (Budget(views=3, metres=1.5), 3),
        (Budget(views=5, metres=1.5), 4),
    ],
)
def test_budget_truncates_the_visit(refined_hand: RefinedScene, budget: Budget, kept: int) -> None:
    episode = _run(refined_hand, 0, PATH, ordered=True, budget=budget)
    assert episode.visited == (0, *PATH)[:kept]
    assert episode.views == kept
    assert episode.step_metres == pytest.approx(STEPS[: kept - 1], rel=1e-12)
    assert episode.coverage_curve == pytest.approx(CURVE[:kept])
    assert episode.coverage == pytest.approx(CURVE[kept - 1])
    assert episode.planned == PATH  # the plan itself is not cut
    if budget.metres is not None:
        assert episode.movement <= budget.metres + 1e-12


def test_budget_cuts_a_one_shot_visit_after_ordering(refined_hand: RefinedScene) -> None:
    """The set is ordered first (0 → 1 → 2 → 3), then cut: the budget does not change which views come first."""
    episode = _run(refined_hand, 0, (3, 2, 1), ordered=False, budget=Budget(views=3))
    assert episode.visited == (0, 1, 2)
    episode = _run(refined_hand, 0, (3, 2, 1), ordered=False, budget=Budget(metres=2.5 * CHORD_60))
    assert episode.visited == (0, 1, 2)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"views": 0},
        {"views": -3},
        {"metres": 0.0},
        {"metres": -1.0},
        {"metres": math.nan},
        {"metres": math.inf},
    ],
)
def test_invalid_budget_raises(kwargs: dict[str, float]) -> None:
    with pytest.raises(InvalidArgument, match="budget") as info:
        Budget(**kwargs)
    assert "\n" not in str(info.value)


# --- Chamfer -----------------------------------------------------------------------------------------------


def test_chamfer_hand_values() -> None:
    rng = np.random.default_rng(3)
    cloud = rng.uniform(-0.05, 0.05, size=(40, 3))
    assert chamfer_mm(cloud, cloud) == 0.0
    # Two points 10 mm apart, shifted by 1 mm along the line between them: every nearest distance is 1 mm.
    a = np.array([[0.0, 0.0, 0.0], [0.010, 0.0, 0.0]])
    assert chamfer_mm(a + np.array([0.0, 0.001, 0.0]), a) == pytest.approx(1.0, rel=1e-9)
    assert chamfer_mm(a, a + np.array([0.0, 0.0, 0.001])) == pytest.approx(1.0, rel=1e-9)
    # One observed point at the origin, truth at 0 and 3 mm: forward 0, backward (0 + 3)/2 → mean 0.75 mm.
    assert chamfer_mm([[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.003, 0.0, 0.0]]) == pytest.approx(0.75, rel=1e-9)
    # Symmetric in its arguments.
    assert chamfer_mm([[0.0, 0.0, 0.0], [0.003, 0.0, 0.0]], [[0.0, 0.0, 0.0]]) == pytest.approx(0.75, rel=1e-9)
    # Against a brute-force mean of nearest distances.
    b = rng.uniform(-0.05, 0.05, size=(25, 3))
    d = np.linalg.norm(cloud[:, None, :] - b[None, :, :], axis=2)
    expected = 1000.0 * (d.min(axis=1).mean() + d.min(axis=0).mean()) / 2
    assert chamfer_mm(cloud, b) == pytest.approx(expected, rel=1e-12)


def test_chamfer_of_nothing_is_nan() -> None:
    assert math.isnan(chamfer_mm(np.empty((0, 3)), [[0.0, 0.0, 0.0]]))
    assert math.isnan(chamfer_mm([[0.0, 0.0, 0.0]], np.empty((0, 3))))


# --- open_path_heuristic and visit_order -------------------------------------------------------------------


def _cost(w: np.ndarray, order: list[int]) -> float:
    return sum(float(w[a, b]) for a, b in itertools.pairwise(order))


@pytest.mark.parametrize("n", range(5, 10))
def test_heuristic_never_beats_held_karp(n: int) -> None:
    rng = np.random.default_rng(500 + n)
    for trial in range(4):
        if trial % 2:
            w = rng.uniform(0.1, 2.0, size=(n, n))
            w = (w + w.T) / 2
            np.fill_diagonal(w, 0.0)
        else:  # metric: distances between random points
            p = rng.normal(size=(n, 3))
            w = np.linalg.norm(p[:, None] - p[None, :], axis=2)
        start = int(rng.integers(n))
        order, cost = open_path_heuristic(w, start=start)
        assert order[0] == start and sorted(order) == list(range(n))
        assert cost == pytest.approx(_cost(w, order), rel=1e-12)
        assert cost >= held_karp(w, start=start)[1] - 1e-12
        # 2-opt has run to the end: no reversal of a stretch after the start shortens the path.
        for i, j in itertools.combinations(range(1, n), 2):
            assert _cost(w, order[:i] + order[i : j + 1][::-1] + order[j + 1 :]) >= cost - 1e-12


def test_two_opt_repairs_nearest_neighbour() -> None:
    """Points on a line at 8, 1, 7, 9, start at 8: nearest neighbour goes 8 → 7 → 9 → 1 (1 + 2 + 8 = 11);
    reversing the stretch 7, 9 gives 8 → 9 → 7 → 1 (1 + 2 + 6 = 9), the optimum."""
    x = np.array([8.0, 1.0, 7.0, 9.0])
    w = np.abs(x[:, None] - x[None, :])
    assert open_path_heuristic(w, start=0) == ([0, 3, 2, 1], 9.0)
    assert held_karp(w, start=0) == ([0, 3, 2, 1], 9.0)


@pytest.mark.parametrize("n", range(2, 10))
def test_heuristic_is_optimal_on_collinear_points_from_an_end(n: int) -> None:
    rng = np.random.default_rng(900 + n)
    x = rng.uniform(0.0, 1.0, size=n)
    w = np.abs(x[:, None] - x[None, :])
    for start in (int(np.argmin(x)), int(np.argmax(x))):
        order, cost = open_path_heuristic(w, start=start)
        assert cost == pytest.approx(x.max() - x.min(), rel=1e-12)
        assert cost == pytest.approx(held_karp(w, start=start)[1], rel=1e-12)
        assert list(x[order]) == sorted(x, reverse=start == int(np.argmax(x)))


def test_heuristic_is_deterministic_and_handles_trivial_cases() -> None:
    assert open_path_heuristic(np.zeros((1, 1))) == ([0], 0.0)
    assert open_path_heuristic([[0.0, 2.0], [1.0, 0.0]], start=1) == ([1, 0], 1.0)
    # All equal: nearest neighbour takes the lowest index each time and no 2-opt move is strictly shorter.
    assert open_path_heuristic(np.ones((5, 5)), start=2) == ([2, 0, 1, 3, 4], 4.0)
    rng = np.random.default_rng(8)
    w = rng.uniform(size=(12, 12))
    assert open_path_heuristic(w, start=3) == open_path_heuristic(w.copy(), start=3)


@pytest.mark.parametrize(
    ("weights", "start", "match"),
    [
        (np.zeros((3, 4)), 0, "square"),
        (np.zeros((0, 0)), 0, "non-empty"),
        (np.array([[0.0, np.inf], [1.0, 0.0]]), 0, "finite"),
        (np.zeros((3, 3)), 3, "start"),
        (np.zeros((3, 3)), -1, "start"),
    ],
)
def test_heuristic_bad_input(weights: np.ndarray, start: int, match: str) -> None:
    with pytest.raises(InvalidArgument, match=match):
        open_path_heuristic(weights, start=start)


def _sphere_views(n: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_visit_order_is_exact_held_karp_for_small_sets() -> None:
    pos = _sphere_views(32, 1)
    planned = [9, 4, 17, 9, 2, 30, 17]
    order, cost, exact = visit_order(4, planned, pos, np.zeros(3), 0.5)
    assert exact is True
    assert (order, cost) == order_views(4, planned, pos, np.zeros(3), 0.5)
    assert visit_order(4, [], pos, np.zeros(3), 0.5) == ([4], 0.0, True)


def test_visit_order_switches_to_the_heuristic_above_the_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Nodes are counted after dropping duplicates and the initial view. The boundary is checked with a lowered
    limit (a 20-node Held-Karp takes seconds); the real limit stays 20, and 21 real nodes are heuristic."""
    assert path_module.MAX_HELD_KARP_NODES == 20
    pos = _sphere_views(32, 2)
    centre, r = np.zeros(3), 0.5
    order, cost, exact = visit_order(0, list(range(1, 21)), pos, centre, r)  # 21 nodes
    assert exact is False
    assert order[0] == 0 and sorted(order) == list(range(21))
    w = path_matrix(pos, centre, r)
    assert cost == pytest.approx(_cost(w, order), rel=1e-12)

    monkeypatch.setattr(path_module, "MAX_HELD_KARP_NODES", 6)
    five_planned = [7, 3, 7, 0, 12, 3, 20, 25, 0]  # {3, 7, 12, 20, 25} once the initial 0 and repeats go
    order, cost, exact = visit_order(0, five_planned, pos, centre, r)
    assert exact is True
    assert (order, cost) == order_views(0, five_planned, pos, centre, r)
    order, cost, exact = visit_order(0, [*five_planned, 31], pos, centre, r)
    assert exact is False
    assert order[0] == 0 and sorted(order) == [0, 3, 7, 12, 20, 25, 31]
    assert cost == pytest.approx(_cost(w, order), rel=1e-12)
    nodes = [0, 3, 7, 12, 20, 25, 31]
    best = min(_cost(w, [0, *perm]) for perm in itertools.permutations(nodes[1:]))
    assert cost >= best - 1e-12


# --- a real scene --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def refined_real(spec: ObjectSpec, config: GenerationConfig) -> RefinedScene:
    scene = build_scene(prepare_object(spec, config), 0, config, build_view_space(config.view_space))
    return RefinedScene(scene, make_refiner(config), config)


def _check_consistent(episode: Episode, scene: Scene) -> None:
    seen = scene.seen(episode.visited)
    assert episode.observed_size == int(seen.sum())
    assert episode.coverage == pytest.approx(seen.mean(), rel=1e-15)
    assert episode.coverage_gt == pytest.approx(seen.sum() / len(scene.scan.ground_truth), rel=1e-15)
    curve = [scene.seen(episode.visited[: i + 1]).mean() for i in range(episode.views)]
    assert episode.coverage_curve == pytest.approx(curve, rel=1e-15)
    w = path_matrix(scene.positions, np.zeros(3), scene.obstacle_radius)
    assert episode.step_metres == pytest.approx([w[a, b] for a, b in itertools.pairwise(episode.visited)], rel=1e-12)
    expected = chamfer_mm(
        np.concatenate([scene.scan.observations[v].points for v in episode.visited]), scene.scan.ground_truth.points
    )
    assert episode.chamfer_mm == pytest.approx(expected, rel=1e-12)


def test_all_views_on_a_real_scene(refined_real: RefinedScene) -> None:
    scene = refined_real.scene
    episode = run_episode(AllPlanner(), Situation(refined_real, 5))
    assert episode.coverage == 1.0  # the reference is the union of every view's keys
    assert episode.observed_size == scene.reference.size
    assert episode.views == 32 and episode.visited[0] == 5
    assert episode.exact_path is False  # 32 views: too many for Held-Karp
    assert 0.0 < episode.coverage_gt <= 1.0
    _check_consistent(episode, scene)


def test_oracle_episode_on_a_real_scene(refined_real: RefinedScene) -> None:
    situation = Situation(refined_real, 0)
    episode = run_episode(OraclePlanner(), situation, Budget(views=32))
    label = situation.oracle_label()
    assert episode.planned == label.views
    assert sorted(episode.visited[1:]) == sorted(label.views)
    assert episode.exact_path is True and episode.refiner == "none"
    # The oracle reads the refined scene: its input time is the scene's refinement time per view.
    assert episode.input_seconds == pytest.approx(refined_real.refine_seconds / 32)
    assert episode.object_name == "capsule"
    _check_consistent(episode, refined_real.scene)
