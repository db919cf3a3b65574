"""Planners (`datagen.evaluate.planners`): baselines on hand-built scenes against brute force, the oracle on a
real built-in scene against an exhaustive set cover, the trained-network wrapper, and `make_planner`."""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from datagen.errors import DatagenError, PlannerError
from datagen.evaluate.baselines import AllPlanner, RandomPlanner
from datagen.evaluate.episode import run_episode
from datagen.evaluate.oracle import OraclePlanner
from datagen.evaluate.planners import GreedyPlanner, make_planner, planner_help
from datagen.evaluate.protocol import Plan
from datagen.evaluate.scene import Scene
from datagen.evaluate.scored import ScoredPlanner
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.ground_truth import GroundTruth
from datagen.pipeline.imaging import Observation, TaskImaging
from datagen.pipeline.objects.prepare import PreparedObject
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine.factory import make_refiner
from schemas.config import GenerationConfig

HAND_COLUMNS = ([0, 1, 2], [2, 3], [3, 4, 5, 6], [6, 7], [7, 8, 9], [0, 9])
"""Six views over a reference of ten keys: which reference indices each view sees."""


def make_scene(spec: ObjectSpec, columns: tuple[list[int], ...] | list[list[int]], reference_size: int) -> Scene:
    """Views on a circle of radius 0.4 m (z = 0) around an obstacle of 0.1 m, seeing the given reference keys."""
    n = len(columns)
    reference = np.arange(reference_size, dtype=np.int64) * 7 + 3
    points = np.zeros((reference_size, 3))
    points[:, 0] = 0.001 * np.arange(reference_size)
    angles = 2 * np.pi * np.arange(n) / n
    positions = np.stack([0.4 * np.cos(angles), 0.4 * np.sin(angles), np.zeros(n)], axis=1)
    cols = tuple(np.unique(np.asarray(c, dtype=np.int64)) for c in columns)
    observations = tuple(
        Observation(
            views=(v,),
            origins=positions[v : v + 1],
            points=points[c].astype(np.float32),
            point_views=np.full(c.size, v, dtype=np.uint8),
            pixels=np.zeros((c.size, 2), dtype=np.float32),
            keys=reference[c],
        )
        for v, c in enumerate(cols)
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
        rotation=1,
        scan=TaskImaging(
            observations=observations,
            ground_truth=GroundTruth(keys=reference, points=points, sampled=reference_size),
            rays_cast=0,
            seconds=0.0,
        ),
        positions=positions,
        obstacle_radius=0.1,
        reference=reference,
        view_columns=cols,
    )


@pytest.fixture(scope="module")
def hand(spec: ObjectSpec, config: GenerationConfig) -> RefinedScene:
    return RefinedScene(make_scene(spec, HAND_COLUMNS, 10), make_refiner(config), config)


# --- greedy ------------------------------------------------------------------------------------------------


def brute_greedy(keys: list[set[int]], initial: int, total: int | None) -> tuple[int, ...]:
    """Next-best view by new keys, scanning view ids upwards so that a tie keeps the lowest id."""
    seen, taken = set(keys[initial]), [initial]
    limit = len(keys) if total is None else min(total, len(keys))
    while len(taken) < limit:
        best, best_gain = -1, -1
        for v in range(len(keys)):
            gain = len(keys[v] - seen)
            if v not in taken and gain > best_gain:
                best, best_gain = v, gain
        if best_gain == 0 and total is None:
            break
        taken.append(best)
        seen |= keys[best]
    return tuple(taken[1:])


@pytest.mark.parametrize(
    ("initial", "total", "expected"),
    [
        # From 0 ({0,1,2}): gains 1, 4, 2, 3, 1 → view 2; then 0, -, 1, 3, 1 → view 4; then nothing new.
        (0, None, (2, 4)),
        (0, 1, ()),
        (0, 2, (2,)),
        (0, 3, (2, 4)),
        # greedy:K goes on at zero gain, lowest id first.
        (0, 5, (2, 4, 1, 3)),
        (0, 6, (2, 4, 1, 3, 5)),
        (0, 40, (2, 4, 1, 3, 5)),
        # From 3 ({6,7}): views 0 and 2 both add 3 keys, the tie goes to 0; then 2 (3 new), then 4 (2 new).
        (3, None, (0, 2, 4)),
        (3, 2, (0,)),
    ],
)
def test_greedy_hand_cases(hand: RefinedScene, initial: int, total: int | None, expected: tuple[int, ...]) -> None:
    plan = GreedyPlanner(total).plan(Situation(hand, initial))
    assert plan == Plan(views=expected, ordered=True)


def test_greedy_matches_brute_force_on_random_scenes(spec: ObjectSpec, config: GenerationConfig) -> None:
    rng = np.random.default_rng(12)
    refiner = make_refiner(config)
    for trial in range(12):
        n, size = int(rng.integers(3, 10)), int(rng.integers(5, 40))
        columns = [list(rng.choice(size, size=int(rng.integers(0, size // 2 + 2)), replace=True)) for _ in range(n)]
        if trial % 4 == 0:
            columns[0] = list(range(size))  # one view sees everything
        refined = RefinedScene(make_scene(spec, columns, size), refiner, config)
        keys = [set(c) for c in columns]
        for initial in range(n):
            for total in (None, 1, 2, n - 1, n, n + 3):
                plan = GreedyPlanner(total).plan(Situation(refined, initial))
                assert plan.ordered is True
                assert plan.views == brute_greedy(keys, initial, total), (trial, initial, total)


def test_plain_greedy_covers_a_real_scene(real: RefinedScene) -> None:
    scene = real.scene
    keys = [set(o.keys.tolist()) for o in scene.scan.observations]
    for initial in (0, 13, 31):
        situation = Situation(real, initial)
        plan = GreedyPlanner().plan(situation)
        assert plan.views == brute_greedy(keys, initial, None)
        episode = run_episode(GreedyPlanner(), situation)
        assert episode.visited == (initial, *plan.views)  # ordered: visited as chosen
        assert episode.coverage == 1.0  # stops only when no view adds a key of the reference
        assert all(b > a for a, b in itertools.pairwise(episode.coverage_curve))  # every view added something
        assert episode.refiner == "-"
        # greedy:3 makes the same first choices, then stops at three views in all.
        capped = GreedyPlanner(3).plan(situation).views
        assert len(capped) == 2 and capped[: len(plan.views)] == plan.views[:2]


# --- random ------------------------------------------------------------------------------------------------


def test_random_k_is_seeded_and_excludes_the_initial_view(hand: RefinedScene, config: GenerationConfig) -> None:
    scene = hand.scene
    for initial in range(6):
        plan = RandomPlanner(3).plan(Situation(hand, initial))
        assert len(plan.views) == 2 and initial not in plan.views
        assert list(plan.views) == sorted(set(plan.views)) and plan.ordered is False
        # Same situation, fresh objects or the same one again: the same views.
        situation = Situation(hand, initial)
        assert RandomPlanner(3).plan(situation) == RandomPlanner(3).plan(situation) == plan
        # Exactly the evaluation stream of this (object, rotation, initial view).
        others = [v for v in range(6) if v != initial]
        rng = stream(config.seed, scene.object_id, scene.rotation, Purpose.EVALUATION, mask=1 << initial)
        assert plan.views == tuple(sorted(others[i] for i in rng.choice(5, size=2, replace=False)))


def test_random_streams_differ_between_initial_views(hand: RefinedScene) -> None:
    draws = [Situation(hand, v).rng().random(16) for v in range(6)]
    for a, b in itertools.combinations(range(6), 2):
        assert not np.array_equal(draws[a], draws[b])
    # rng() is a fresh stream each call.
    assert np.array_equal(Situation(hand, 2).rng().random(16), draws[2])


def test_random_k_bounds(hand: RefinedScene) -> None:
    assert RandomPlanner(1).plan(Situation(hand, 4)).views == ()
    assert RandomPlanner(6).plan(Situation(hand, 4)).views == (0, 1, 2, 3, 5)
    assert RandomPlanner(99).plan(Situation(hand, 4)).views == (0, 1, 2, 3, 5)


def test_plain_random_takes_as_many_views_as_the_oracle(real: RefinedScene) -> None:
    for initial in range(0, 32, 5):
        situation = Situation(real, initial)
        plan = RandomPlanner().plan(situation)
        label = situation.oracle_label()
        assert len(plan.views) == label.objective == len(label.views) > 0
        assert initial not in plan.views and len(set(plan.views)) == len(plan.views)
        assert all(0 <= v < 32 for v in plan.views)


# --- all ---------------------------------------------------------------------------------------------------


def test_all_takes_every_other_view(hand: RefinedScene) -> None:
    assert AllPlanner().plan(Situation(hand, 3)) == Plan(views=(0, 1, 2, 4, 5), ordered=False)


def test_all_covers_the_whole_reference_of_a_real_scene(real: RefinedScene) -> None:
    episode = run_episode(AllPlanner(), Situation(real, 9))
    assert sorted(episode.visited) == list(range(32))
    assert episode.coverage == 1.0
    assert episode.observed_size == real.scene.reference.size


# --- oracle ------------------------------------------------------------------------------------------------


def _or_masks(combos: list[tuple[int, ...]]) -> npt.NDArray[np.uint64]:
    out = np.zeros(len(combos), dtype=np.uint64)
    for i, combo in enumerate(combos):
        for v in combo:
            out[i] |= np.uint64(1) << np.uint64(v)
    return out


def test_oracle_is_a_minimum_cover_on_a_real_scene(real: RefinedScene) -> None:
    """For every initial view: the label with the initial view covers all of P_full, and enumerating every set of
    other views in lexicographic order, the first that covers has the label's size and views."""
    coverage = real.coverage
    assert len(coverage) > 0
    sizes = []
    for initial in range(32):
        situation = Situation(real, initial)
        label = situation.oracle_label()
        case = 1 << initial
        assert label.label & case == 0
        assert coverage.covered_by(case | label.label).all()
        assert not coverage.covered_by(case).all()
        assert OraclePlanner().plan(situation) == Plan(views=label.views)
        rows = np.unique(coverage.masks[(coverage.masks & np.uint64(case)) == 0])
        others = [v for v in range(32) if v != initial]
        first = None
        for size in range(label.objective + 1):
            combos = list(itertools.combinations(others, size))
            covering = ((_or_masks(combos)[:, None] & rows[None, :]) != 0).all(axis=1)
            if covering.any():
                first = combos[int(np.argmax(covering))]
                break
        assert first is not None and len(first) == label.objective, initial
        assert first == label.views, initial
        sizes.append(label.objective)
    assert max(sizes) <= 3  # the brute force above stays small


def test_oracle_episode_reads_the_refiner(real: RefinedScene) -> None:
    episode = run_episode(OraclePlanner(), Situation(real, 4))
    assert episode.refiner == "none" and episode.planner == "oracle"
    assert sorted(episode.visited[1:]) == sorted(Situation(real, 4).oracle_label().views)


# --- a trained network -------------------------------------------------------------------------------------


class FixedScorer:
    """Returns fixed probabilities and records what it was asked."""

    def __init__(self, probabilities: npt.ArrayLike) -> None:
        self.probabilities = np.asarray(probabilities)
        self.calls: list[tuple[np.ndarray, np.ndarray]] = []

    def view_probabilities(self, points: np.ndarray, view_state: np.ndarray) -> np.ndarray:
        self.calls.append((points, view_state))
        return self.probabilities


def test_scored_planner_keeps_views_above_one_half(real: RefinedScene) -> None:
    p = np.full(32, 0.1)
    p[[3, 7, 9, 12, 20]] = [0.9, 0.99, 0.5, 0.5000001, 0.51]  # 3 is the initial view; 0.5 itself is not chosen
    scorer = FixedScorer(p)
    situation = Situation(real, 3)
    plan = ScoredPlanner("net", scorer).plan(situation)
    assert plan.views == (7, 12, 20) and plan.ordered is False
    assert plan.probabilities is not None and np.array_equal(plan.probabilities, p)
    (points, state), *_ = scorer.calls
    request = situation.request()
    assert points.ndim == 2 and points.shape[1] == 3 and points.shape[0] > 0
    assert np.array_equal(points, request.points)
    assert state.shape == (32,) and state[3] == 1.0 and state.sum() == 1.0
    episode = run_episode(ScoredPlanner("net", FixedScorer(p)), situation)
    assert episode.planner == "net" and episode.refiner == "none"
    assert sorted(episode.visited) == [3, 7, 12, 20]


@pytest.mark.parametrize("shape", [(31,), (33,), (1, 32)])
def test_scored_planner_rejects_wrong_length(real: RefinedScene, shape: tuple[int, ...]) -> None:
    planner = ScoredPlanner("net", FixedScorer(np.full(shape, 0.9)))
    with pytest.raises(PlannerError, match="another view space") as info:
        planner.plan(Situation(real, 0))
    assert "\n" not in str(info.value)


# --- make_planner ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec_text", "kind", "total", "uses_refinement"),
    [
        ("oracle", OraclePlanner, None, True),
        ("all", AllPlanner, None, False),
        ("greedy", GreedyPlanner, None, False),
        ("greedy:4", GreedyPlanner, 4, False),
        ("greedy:1", GreedyPlanner, 1, False),
        ("random", RandomPlanner, None, True),
        ("random:7", RandomPlanner, 7, False),
    ],
)
def test_make_planner_resolves(spec_text: str, kind: type, total: int | None, uses_refinement: bool) -> None:
    planner = make_planner(spec_text)
    assert isinstance(planner, kind)
    assert planner.name == spec_text
    assert planner.uses_refinement is uses_refinement
    if total is not None or kind in (GreedyPlanner, RandomPlanner):
        assert planner.total_views == total  # type: ignore[attr-defined]


@pytest.mark.parametrize("spec_text", ["", "nope", "Oracle", "greedy4", "cheat:2"])
def test_make_planner_unknown_names_the_choices(spec_text: str) -> None:
    with pytest.raises(PlannerError, match="unknown planner") as info:
        make_planner(spec_text)
    assert planner_help() in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("spec_text", "message"),
    [
        ("all:3", "planner 'all:3': 'all' takes no argument; write all"),
        ("greedy+size:3", "planner 'greedy+size:3': only a plugin's scorer takes +DECODING; write greedy:K"),
        ("osvp", "planner 'osvp': give osvp:ARG (for example a checkpoint)"),
        ("random:", "planner 'random:' names nothing after ':'"),
    ],
)
def test_make_planner_refuses_what_a_planner_cannot_take(spec_text: str, message: str) -> None:
    with pytest.raises(PlannerError) as info:
        make_planner(spec_text)
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


@pytest.mark.parametrize("spec_text", ["greedy:0", "greedy:x", "greedy:-2", "random:0", "random:1.5", "random:two"])
def test_make_planner_bad_view_count(spec_text: str) -> None:
    with pytest.raises(PlannerError, match="K must be a whole number of views >= 1") as info:
        make_planner(spec_text)
    assert repr(spec_text) in str(info.value)


@pytest.mark.skipif(importlib.util.find_spec("osvp") is None, reason="the osvp package is not installed")
def test_make_planner_missing_checkpoint(tmp_path: Path) -> None:
    """osvp's factory (the ``osvp`` planner plugin) refuses the path; its error goes through as it is."""
    missing = tmp_path / "missing" / "model.pt"
    with pytest.raises(DatagenError, match="checkpoint not found") as info:
        make_planner(f"osvp:{missing}")
    assert str(missing) in str(info.value) and "osvp train" in str(info.value)
    with pytest.raises(DatagenError, match="checkpoint not found"):
        make_planner(f"osvp:{tmp_path}")  # a folder is not a checkpoint


def test_make_planner_without_the_osvp_package(tmp_path: Path, no_plugins: None) -> None:
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"not really a checkpoint")
    with pytest.raises(PlannerError, match="unknown planner 'osvp:") as info:
        make_planner(f"osvp:{checkpoint}")
    assert "\n" not in str(info.value)
