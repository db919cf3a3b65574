"""One simulated run: ask a planner, order its views, visit them, and measure what was observed.

The camera starts at the initial view (already taken). A one-shot set is visited along the shortest
open path from there (`datagen.evaluate.path.visit_order`); an iterative planner's views in its own
order. Each move costs the local path around the obstacle sphere. Budgets cut the visit short: at most
``views`` views in all (the initial one included) and at most ``metres`` of movement (a move that would
exceed it is not made).

Figures (docs/authors-code.md section 8): coverage = distinct observed keys / keys visible from
all candidate views (the authors' reference count); ``coverage_gt`` = the same over every key of P_gt;
required views counts the initial view; coverage per view and per metre are the paper's efficiency
columns (percent per view, percent per metre). A planner that looks at the object also carries the
coverage of random views, of the best fixed set and of spread views at its own view count in the same
situation: its lifts over chance, over the constant plan and over a data-free plan that knows only the
initial view, at equal views. Where the planner can answer for any view count
(`Plan.at_count`), the run keeps its coverage at every count (``count_curve``): how many views it
needs to reach a share (`views_to`).
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from datagen.errors import InvalidArgument
from datagen.evaluate.path import path_matrix, visit_order
from datagen.evaluate.protocol import Plan, Planner
from datagen.evaluate.scene import Scene
from datagen.evaluate.situation import Situation

ORIGIN = np.zeros(3)


@dataclass(frozen=True)
class Budget:
    """Limits of one run; None means unlimited."""

    views: int | None = None
    """Most views in all, the initial view included."""
    metres: float | None = None
    """Most movement, metres."""

    def __post_init__(self) -> None:
        if self.views is not None and self.views < 1:
            raise InvalidArgument(f"view budget {self.views} must be >= 1 (the initial view counts)")
        if self.metres is not None and not (np.isfinite(self.metres) and self.metres > 0):
            raise InvalidArgument(f"movement budget {self.metres} must be a positive number of metres")


@dataclass(frozen=True)
class Episode:
    """The outcome of one planner on one (object, rotation, initial view, refiner)."""

    object_name: str
    object_id: str
    rotation: int
    initial_view: int
    refiner: str
    """The refiner of the planner's input and labels; "-" for planners that use neither."""
    planner: str
    planned: tuple[int, ...]
    """The planner's views exactly as it returned them (`visited` drops the initial view and repeats)."""
    visited: tuple[int, ...]
    """Views in the order visited, the initial view first, after the budgets."""
    step_metres: tuple[float, ...]
    """Cost of each move (len(visited) - 1)."""
    coverage_curve: tuple[float, ...]
    """Coverage (fraction of the reference) after each visited view."""
    reference_size: int
    ground_truth_size: int
    observed_size: int
    exact_path: bool
    """False when the set was too large for Held-Karp and a heuristic ordered it."""
    planning_seconds: float
    """The planner's own call (for the oracle: the exact set-cover solve)."""
    input_seconds: float
    """Refining the input view (`Situation.input_seconds`); 0 for planners that read no input."""
    chamfer_mm: float
    matched_random_coverage: float | None = None
    """Coverage (fraction) of random views at this run's view count in the same situation (None for the
    baselines themselves)."""
    matched_fixed_coverage: float | None = None
    """Coverage (fraction) of the best fixed set at this run's view count (None without fixed plans)."""
    matched_spread_coverage: float | None = None
    """Coverage (fraction) of views spread from the initial view (no data) at this run's view count."""
    count_curve: tuple[float, ...] | None = None
    """Coverage (fraction) of the initial view plus the planner's answer for c new views, c = 0..n-1, where
    the planner answers for any count (None otherwise); no budget applies."""
    ordered: bool = False
    """Whether the planner decided the order of its views (a step-by-step player): then its coverage
    after its first c views is its answer for c views (`datagen.evaluate.margins`)."""

    @property
    def coverage(self) -> float:
        return self.observed_size / self.reference_size if self.reference_size else 0.0

    @property
    def coverage_gt(self) -> float:
        return self.observed_size / self.ground_truth_size if self.ground_truth_size else 0.0

    @property
    def lift(self) -> float:
        """Coverage points above the matched random's in the same situation (NaN without one)."""
        if self.matched_random_coverage is None:
            return float("nan")
        return 100.0 * (self.coverage - self.matched_random_coverage)

    @property
    def lift_fixed(self) -> float:
        """Coverage points above the best fixed set at equal views in the same situation (NaN without one)."""
        if self.matched_fixed_coverage is None:
            return float("nan")
        return 100.0 * (self.coverage - self.matched_fixed_coverage)

    @property
    def lift_spread(self) -> float:
        """Coverage points above spread views at equal views in the same situation (NaN without them)."""
        if self.matched_spread_coverage is None:
            return float("nan")
        return 100.0 * (self.coverage - self.matched_spread_coverage)

    def views_to(self, share: float) -> float:
        """Views (the initial one included) the planner needs to see ``share`` of the reference, from its
        answers at every count; NaN where it cannot say."""
        if self.count_curve is None:
            return float("nan")
        reached = [c for c, coverage in enumerate(self.count_curve) if coverage >= share - 1e-12]
        return float(reached[0] + 1) if reached else float("nan")

    @property
    def views(self) -> int:
        return len(self.visited)

    @property
    def movement(self) -> float:
        return float(sum(self.step_metres))

    @property
    def coverage_per_view(self) -> float:
        """Percent of the reference per required view."""
        return 100.0 * self.coverage / self.views

    @property
    def coverage_per_metre(self) -> float:
        """Percent of the reference per metre moved (NaN when the camera never moved)."""
        return 100.0 * self.coverage / self.movement if self.movement > 0 else float("nan")

    def as_dict(self) -> dict[str, object]:
        """The run as plain data (JSON output): what was planned and visited, and its figures."""
        data: dict[str, object] = {
            name: getattr(self, name)
            for name in ("object_name", "object_id", "rotation", "initial_view", "refiner", "planner")
        }
        data.update(planned=list(self.planned), visited=list(self.visited), exact_path=self.exact_path)
        data.update(ordered=self.ordered)
        data.update(step_metres=[round(s, 6) for s in self.step_metres])
        data.update(coverage_curve=[round(c, 6) for c in self.coverage_curve])
        data.update(reference_size=self.reference_size, ground_truth_size=self.ground_truth_size)
        data.update(observed_size=self.observed_size)
        for name in ("matched_random_coverage", "matched_fixed_coverage", "matched_spread_coverage"):
            matched = getattr(self, name)
            data[name] = None if matched is None else round(100.0 * matched, 6)
        curve = self.count_curve
        data.update(count_curve=None if curve is None else [round(c, 6) for c in curve])
        data.update({k: (None if v != v else round(v, 6)) for k, v in self.figures().items()})
        return data

    def figures(self, tau: float | None = None) -> dict[str, float]:
        """The per-run numbers the tables average (``tau``: also the views needed to see that share)."""
        return {
            "views_to_tau": self.views_to(tau) if tau is not None else float("nan"),
            "coverage": 100.0 * self.coverage,
            "coverage_gt": 100.0 * self.coverage_gt,
            "lift": self.lift,
            "lift_fixed": self.lift_fixed,
            "lift_spread": self.lift_spread,
            "views": float(self.views),
            "movement": self.movement,
            "coverage_per_view": self.coverage_per_view,
            "coverage_per_metre": self.coverage_per_metre,
            "planning_seconds": self.planning_seconds,
            "input_seconds": self.input_seconds,
            "chamfer_mm": self.chamfer_mm,
        }


def run_episode(planner: Planner, situation: Situation, budget: Budget = Budget(), measure: bool = True) -> Episode:
    """Plan, order, visit and measure one run (``measure=False``: coverage only, no Chamfer distance and no
    coverage by view count, for the baselines a run is compared with)."""
    if planner.uses_refinement:
        situation.prepare()
    started = time.perf_counter()
    plan = planner.plan(situation)
    planning = time.perf_counter() - started
    scene = situation.scene
    order, steps, exact = _route(scene, situation.initial_view, plan)
    order, steps = _within_budget(order, steps, budget)
    seen = np.zeros(scene.reference.size, dtype=bool)
    curve = []
    for view in order:
        seen[scene.view_columns[view]] = True
        curve.append(float(np.count_nonzero(seen)) / scene.reference.size if scene.reference.size else 0.0)
    return Episode(
        object_name=scene.object_name,
        object_id=scene.object_id,
        rotation=scene.rotation,
        initial_view=situation.initial_view,
        refiner=situation.refined.refiner.name if planner.uses_refinement else "-",
        planner=planner.name,
        planned=tuple(int(v) for v in plan.views),
        visited=tuple(order),
        step_metres=tuple(steps),
        coverage_curve=tuple(curve),
        reference_size=int(scene.reference.size),
        ground_truth_size=scene.ground_truth_size,
        observed_size=int(np.count_nonzero(seen)),
        exact_path=exact,
        planning_seconds=planning,
        input_seconds=situation.input_seconds if planner.uses_refinement else 0.0,
        chamfer_mm=chamfer_mm(scene.observed_points(order), scene.scan.ground_truth.points) if measure else math.nan,
        count_curve=_count_curve(scene, situation.initial_view, plan) if measure else None,
        ordered=plan.ordered,
    )


def _count_curve(scene: Scene, initial: int, plan: Plan) -> tuple[float, ...] | None:
    """Coverage of the initial view plus the plan's answer for c new views, for every c (no budget)."""
    if plan.at_count is None or not scene.reference.size:
        return None
    curve = []
    for count in range(scene.num_views):
        views = [initial, *plan.at_count(count)]
        curve.append(float(np.count_nonzero(scene.seen(views))) / scene.reference.size)
    return tuple(curve)


def chamfer_mm(observed: npt.ArrayLike, truth: npt.ArrayLike) -> float:
    """Symmetric Chamfer distance in millimetres: the mean of (mean nearest distance observed -> truth) and
    (truth -> observed). The second term grows with what was never seen, so it measures completeness too."""
    a = np.asarray(observed, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(truth, dtype=np.float64).reshape(-1, 3)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return float("nan")
    forward = cKDTree(b).query(a)[0].mean()
    backward = cKDTree(a).query(b)[0].mean()
    return 1000.0 * float(forward + backward) / 2.0


def _route(scene: Scene, initial: int, plan: Plan) -> tuple[list[int], list[float], bool]:
    """Visiting order (initial first) and the cost of each move."""
    planned = [int(v) for v in plan.views]
    bad = [v for v in planned if not (0 <= v < scene.num_views)]
    if bad:
        raise InvalidArgument(f"planner returned view {bad[0]}, outside 0..{scene.num_views - 1}")
    if plan.ordered:
        order = [initial, *dict.fromkeys(v for v in planned if v != initial)]
        exact = True
    else:
        order, _, exact = visit_order(initial, planned, scene.positions, ORIGIN, scene.obstacle_radius)
    weights = path_matrix(scene.positions[order], ORIGIN, scene.obstacle_radius)
    steps = [float(weights[i, i + 1]) for i in range(len(order) - 1)]
    return order, steps, exact


def _within_budget(order: list[int], steps: list[float], budget: Budget) -> tuple[list[int], list[float]]:
    if budget.views is not None:
        order = order[: budget.views]
        steps = steps[: len(order) - 1]
    if budget.metres is not None:
        spent = list(itertools.accumulate(steps))
        keep = sum(1 for total in spent if total <= budget.metres + 1e-12)
        order, steps = order[: keep + 1], steps[:keep]
    return order, steps
