"""Evaluation figures: coverage within a budget by hand, the drawn local path against its length, PNGs."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from datagen.errors import InvalidArgument
from datagen.evaluate.episode import Episode
from datagen.evaluate.figures import (
    _local_path_points,
    coverage_at_budgets,
    draw_budget_curves,
    draw_object,
    row_label,
)
from datagen.evaluate.path import local_path_length, path_matrix
from datagen.evaluate.scene import Scene, build_scene
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

ORIGIN = np.zeros(3)


def episode(
    steps: tuple[float, ...] = (0.5, 0.3),
    curve: tuple[float, ...] = (0.4, 0.7, 0.9),
    visited: tuple[int, ...] | None = None,
    planner: str = "greedy",
    refiner: str = "-",
) -> Episode:
    visited = tuple(range(len(curve))) if visited is None else visited
    return Episode(
        object_name="capsule",
        object_id="id-capsule",
        rotation=0,
        initial_view=visited[0],
        refiner=refiner,
        planner=planner,
        planned=visited[1:],
        visited=visited,
        step_metres=steps,
        coverage_curve=curve,
        reference_size=1000,
        ground_truth_size=1200,
        observed_size=round(1000 * curve[-1]),
        exact_path=True,
        planning_seconds=0.01,
        input_seconds=0.0,
        chamfer_mm=1.5,
    )


def png_size(path: Path) -> tuple[int, int]:
    with Image.open(path) as image:
        assert image.format == "PNG"
        image.load()
        return image.size


# -- coverage within a budget --------------------------------------------------------------------


def test_coverage_at_budgets_by_hand() -> None:
    got = coverage_at_budgets(episode(), np.array([0.0, 0.49, 0.5, 0.79, 0.8, 10.0]))
    np.testing.assert_array_equal(got, [0.4, 0.4, 0.7, 0.7, 0.9, 0.9])


def test_coverage_at_budgets_negative_budget_and_no_moves() -> None:
    np.testing.assert_array_equal(coverage_at_budgets(episode(), np.array([-1.0])), [0.4])
    still = episode(steps=(), curve=(0.25,))
    np.testing.assert_array_equal(coverage_at_budgets(still, np.array([0.0, 1.0, 5.0])), [0.25, 0.25, 0.25])


def test_coverage_at_budgets_total_movement_reaches_the_last_view() -> None:
    """0.1 + 0.1 + 0.1 rounds differently summed in numpy and in Python; the total still buys every view."""
    run = episode(steps=(0.1, 0.1, 0.1), curve=(0.1, 0.2, 0.3, 0.4))
    assert coverage_at_budgets(run, np.array([run.movement]))[0] == 0.4
    np.testing.assert_array_equal(coverage_at_budgets(run, np.array([0.15, 0.25])), [0.2, 0.3])


def test_coverage_at_budgets_rejects_a_curve_of_the_wrong_length() -> None:
    with pytest.raises(InvalidArgument, match="coverage values"):
        coverage_at_budgets(episode(steps=(0.5,), curve=(0.4, 0.7, 0.9)), np.array([0.0]))


def test_row_label() -> None:
    assert row_label(episode(planner="greedy")) == "greedy"
    assert row_label(episode(planner="oneshot", refiner="poco")) == "oneshot (poco)"


# -- the drawn local path ------------------------------------------------------------------------


def polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


@pytest.mark.parametrize(
    ("start", "end"),
    [
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # chord through the ball: arc
        ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)),  # through the centre: antipodal entry and exit
        ((0.0, 0.0, 1.0), (0.0, 0.0, -1.0)),  # the same along z (the fallback axis differs)
        ((1.0, 0.3, 0.0), (1.0, -0.3, 0.0)),  # misses the sphere: straight
        ((1.0, 0.5, 0.2), (-1.0, 0.5, 0.2)),  # grazes: touches at the foot, straight
        ((0.8, 0.8, 0.8), (-0.5, 0.9, -0.1)),
        ((0.5, 0.0, 0.0), (0.0, 0.5, 0.0)),  # both endpoints on the sphere
        ((1.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # no move
    ],
)
def test_drawn_local_path_agrees_with_its_length(start: tuple[float, ...], end: tuple[float, ...]) -> None:
    radius = 0.5
    points = _local_path_points(np.array(start), np.array(end), radius)
    np.testing.assert_allclose(points[0], start)
    np.testing.assert_allclose(points[-1], end)
    assert np.linalg.norm(points, axis=1).min() >= radius * (1 - 1e-9)
    expected = local_path_length(start, end, ORIGIN, radius)
    assert polyline_length(points) == pytest.approx(expected, rel=0.01, abs=1e-12)


def test_drawn_local_path_agrees_on_random_view_pairs() -> None:
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(30, 3))
    positions = 0.4 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    radius = 0.3
    lengths = path_matrix(positions, ORIGIN, radius)
    for i, j in itertools.combinations(range(len(positions)), 2):
        points = _local_path_points(positions[i], positions[j], radius)
        assert polyline_length(points) == pytest.approx(lengths[i, j], rel=0.01)
        assert np.linalg.norm(points, axis=1).min() >= radius * (1 - 1e-9)


# -- pictures ------------------------------------------------------------------------------------


def test_draw_budget_curves_writes_a_png(tmp_path: Path) -> None:
    runs = [
        episode(planner="greedy"),
        episode(steps=(0.2, 0.9, 0.1), curve=(0.3, 0.5, 0.8, 0.95), planner="greedy"),
        episode(steps=(1.4,), curve=(0.4, 0.85), planner="oneshot", refiner="poco"),
        episode(steps=(), curve=(0.4,), planner="random"),
    ]
    target = tmp_path / "new" / "folder" / "budget.png"
    draw_budget_curves(runs, target)
    assert png_size(target) == (800, 500)


def test_draw_budget_curves_when_no_run_moved(tmp_path: Path) -> None:
    target = tmp_path / "still.png"
    draw_budget_curves([episode(steps=(), curve=(0.4,))], target)
    assert png_size(target) == (800, 500)


def test_budget_curves_of_nothing_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgument):
        draw_budget_curves([], tmp_path / "a.png")
    assert not list(tmp_path.iterdir())


def test_draw_object_without_runs_still_draws_the_views(tmp_path: Path, capsule_scene: Scene) -> None:
    """Every planner may fail on a scene; the picture then shows the candidate views alone."""
    target = tmp_path / "empty.png"
    draw_object(capsule_scene, [], target)
    assert png_size(target) == (450, 530)


@pytest.fixture(scope="module")
def capsule_scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    listing = tmp_path_factory.mktemp("capsule") / "objects.txt"
    listing.write_text("builtin:capsule\n")
    (spec,) = read_objects_file(listing).objects
    config = GenerationConfig(refiner="none")
    view_space = build_view_space(config.view_space)
    return build_scene(prepare_object(spec, config), 0, config, view_space)


def scene_episode(scene: Scene, visited: tuple[int, ...], planner: str) -> Episode:
    steps = tuple(
        local_path_length(scene.positions[a], scene.positions[b], ORIGIN, scene.obstacle_radius)
        for a, b in itertools.pairwise(visited)
    )
    curve = tuple(float(scene.seen(visited[: k + 1]).mean()) for k in range(len(visited)))
    return episode(steps=steps, curve=curve, visited=visited, planner=planner)


@pytest.mark.parametrize(("panels", "size"), [(1, (450, 530)), (2, (900, 530)), (4, (1350, 980))])
def test_draw_object_writes_a_png(tmp_path: Path, capsule_scene: Scene, panels: int, size: tuple[int, int]) -> None:
    n = capsule_scene.num_views
    routes = [(0, n // 2, n - 1, 3), (0,), (0, 1, 2, 3, 4, 5), (0, n - 1)][:panels]
    runs = [scene_episode(capsule_scene, route, f"planner{k}") for k, route in enumerate(routes)]
    target = tmp_path / "objects" / "capsule.png"
    draw_object(capsule_scene, runs, target)
    assert png_size(target) == size
    with Image.open(target) as image:
        pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    assert len(np.unique(pixels, axis=0)) > 10  # more than a blank page
