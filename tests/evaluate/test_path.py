"""Movement-cost path: local path geometry against hand-computed values, Held-Karp against brute force."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from datagen.errors import InvalidArgument
from datagen.evaluate.path import held_karp, local_path_length, order_views, path_matrix

ORIGIN = np.zeros(3)


def _brute_force(w: np.ndarray, start: int) -> tuple[list[int], float]:
    """Lexicographically first order of minimal cost (permutations come in lexicographic order)."""
    others = [i for i in range(w.shape[0]) if i != start]
    best_order, best_cost = [start], math.inf
    for perm in itertools.permutations(others):
        order = [start, *perm]
        cost = sum(float(w[a, b]) for a, b in itertools.pairwise(order))
        if cost < best_cost:
            best_order, best_cost = order, cost
    return best_order, (0.0 if best_cost == math.inf else best_cost)


def _order_cost(w: np.ndarray, order: list[int]) -> float:
    return sum(float(w[a, b]) for a, b in itertools.pairwise(order))


@pytest.mark.parametrize("n", range(1, 10))
@pytest.mark.parametrize("symmetric", [False, True])
def test_held_karp_matches_brute_force(n: int, symmetric: bool) -> None:
    rng = np.random.default_rng(1000 * n + symmetric)
    for trial in range(3):
        w = rng.uniform(0.1, 2.0, size=(n, n))
        if symmetric:
            w = (w + w.T) / 2
        start = int(rng.integers(n)) if trial else 0
        order, cost = held_karp(w, start=start)
        ref_order, ref_cost = _brute_force(w, start)
        assert order[0] == start and sorted(order) == list(range(n))
        assert order == ref_order  # continuous weights: the optimum is unique
        assert cost == pytest.approx(ref_cost, abs=1e-12)
        assert _order_cost(w, order) == pytest.approx(ref_cost, abs=1e-12)


@pytest.mark.parametrize("n", range(2, 9))
def test_held_karp_tie_break_is_lexicographically_smallest(n: int) -> None:
    """Small integer weights make many exact ties; the rule picks the lexicographically first optimal order."""
    rng = np.random.default_rng(77 + n)
    for _ in range(3):
        w = rng.integers(0, 3, size=(n, n)).astype(np.float64)
        start = int(rng.integers(n))
        assert held_karp(w, start=start) == _brute_force(w, start)


def test_held_karp_all_equal_and_single_node() -> None:
    assert held_karp(np.ones((6, 6)), start=3) == ([3, 0, 1, 2, 4, 5], 5.0)
    assert held_karp(np.zeros((1, 1))) == ([0], 0.0)
    assert held_karp([[0.0, 2.0], [1.0, 0.0]], start=1) == ([1, 0], 1.0)


@pytest.mark.parametrize(
    ("weights", "start", "match"),
    [
        (np.zeros((21, 21)), 0, "at most 20 nodes"),
        (np.zeros((3, 4)), 0, "square"),
        (np.zeros((0, 0)), 0, "non-empty"),
        (np.array([[0.0, np.nan], [1.0, 0.0]]), 0, "finite"),
        (np.zeros((3, 3)), 3, "start"),
    ],
)
def test_held_karp_bad_input(weights: np.ndarray, start: int, match: str) -> None:
    with pytest.raises(InvalidArgument, match=match) as info:
        held_karp(weights, start=start)
    assert "\n" not in str(info.value)


def test_straight_segment_when_it_misses_the_sphere() -> None:
    a, b = np.array([-3.0, 2.0, 0.5]), np.array([3.0, 2.5, -0.5])
    assert local_path_length(a, b, ORIGIN, 1.0) == pytest.approx(np.linalg.norm(b - a), rel=1e-15)
    # Closest approach of the infinite line is inside the sphere but beyond the segment's end: still straight.
    a, b = np.array([-5.0, 0.1, 0.0]), np.array([-2.0, 0.1, 0.0])
    assert local_path_length(a, b, ORIGIN, 1.0) == pytest.approx(3.0, rel=1e-15)
    # Tangent to the sphere: touching is not entering.
    assert local_path_length([-2.0, 1.0, 0.0], [2.0, 1.0, 0.0], ORIGIN, 1.0) == pytest.approx(4.0, rel=1e-15)


def test_collinear_through_centre_is_half_circle() -> None:
    """Start, centre, end collinear: the plane is undefined, any great circle gives the arc π·r."""
    d, r = 3.0, 1.25
    length = local_path_length([-d, 0.0, 0.0], [d, 0.0, 0.0], ORIGIN, r)
    assert length == pytest.approx(2 * (d - r) + math.pi * r, rel=1e-14)
    centre = np.array([0.3, -0.2, 1.0])
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    shifted = local_path_length(centre - d * axis, centre + 2 * d * axis, centre, r)
    assert shifted == pytest.approx((d - r) + math.pi * r + (2 * d - r), rel=1e-13)


def test_chord_geometry_closed_form() -> None:
    """Segment at distance p < r from the centre: entry/exit ±sqrt(r² − p²) from the foot of the perpendicular."""
    r, p, half = 1.0, 0.4, 2.0
    normal = np.array([0.0, 0.6, 0.8])
    along = np.array([1.0, 0.0, 0.0])
    centre = np.array([0.5, -1.0, 2.0])
    start = centre + p * normal - half * along
    end = centre + p * normal + half * along
    h = math.sqrt(r * r - p * p)
    entry = centre + p * normal - h * along
    exit_ = centre + p * normal + h * along
    angle = 2 * math.asin(h / r)
    expected = np.linalg.norm(start - entry) + r * angle + np.linalg.norm(exit_ - end)
    assert local_path_length(start, end, centre, r) == pytest.approx(expected, rel=1e-13)
    assert local_path_length(end, start, centre, r) == pytest.approx(expected, rel=1e-13)


def test_shorter_arc_and_symmetry_on_random_pairs() -> None:
    rng = np.random.default_rng(5)
    r = 0.8
    for _ in range(200):
        dirs = rng.normal(size=(2, 3))
        pts = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(r, 3.0, size=(2, 1))
        ab = local_path_length(pts[0], pts[1], ORIGIN, r)
        ba = local_path_length(pts[1], pts[0], ORIGIN, r)
        assert ab == pytest.approx(ba, rel=1e-12)
        straight = float(np.linalg.norm(pts[1] - pts[0]))
        assert straight - 1e-12 <= ab <= straight - 2 * r + math.pi * r + 1e-12


def test_endpoint_inside_sphere_raises_one_line() -> None:
    with pytest.raises(InvalidArgument, match="inside the obstacle sphere") as info:
        local_path_length([0.1, 0.0, 0.0], [3.0, 0.0, 0.0], ORIGIN, 1.0)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("radius", [-1.0, 0.0, math.nan])
def test_bad_radius_raises(radius: float) -> None:
    with pytest.raises(InvalidArgument, match="radius must be a positive") as info:
        local_path_length([2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], ORIGIN, radius)
    assert "\n" not in str(info.value)
    with pytest.raises(InvalidArgument, match="radius"):
        path_matrix(np.ones((2, 3)) * 3, ORIGIN, radius)


def _sphere_views(n: int, rng: np.random.Generator, dist: float) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True) * dist


def test_path_matrix_agrees_with_local_path_length() -> None:
    rng = np.random.default_rng(11)
    centre, r = np.array([0.1, 0.2, -0.1]), 0.5
    pos = centre + _sphere_views(12, rng, 1.0)
    mat = path_matrix(pos, centre, r)
    assert mat.shape == (12, 12) and mat.dtype == np.float64
    assert np.all(np.diag(mat) == 0.0)
    for i in range(12):
        for j in range(12):
            if i != j:
                assert mat[i, j] == pytest.approx(local_path_length(pos[i], pos[j], centre, r), rel=1e-14)


def test_order_views_initial_first_duplicates_dropped_cost_is_sum() -> None:
    rng = np.random.default_rng(21)
    centre, r = np.zeros(3), 0.6
    pos = _sphere_views(32, rng, 1.0)
    order, cost = order_views(4, [9, 4, 17, 9, 2, 30, 17], pos, centre, r)
    assert order[0] == 4
    assert sorted(order) == [2, 4, 9, 17, 30]
    steps = [local_path_length(pos[a], pos[b], centre, r) for a, b in itertools.pairwise(order)]
    assert cost == pytest.approx(sum(steps), rel=1e-12)
    # The planner's listing order does not matter.
    assert order_views(4, [30, 2, 17, 9], pos, centre, r) == (order, cost)
    assert order_views(4, [], pos, centre, r) == ([4], 0.0)


def test_order_views_bad_view_id() -> None:
    with pytest.raises(InvalidArgument, match="out of range"):
        order_views(0, [32], np.ones((32, 3)) * 2, ORIGIN, 1.0)
