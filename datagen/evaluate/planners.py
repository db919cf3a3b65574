"""Planners `datagen evaluate` compares, behind one small interface.

A planner answers a `Situation` with a `Plan`: either a one-shot set (visited along the shortest open
path) or an ordered sequence (an iterative chooser that already decided the order). Trained networks
plug in as a `ViewScorer` (refined cloud + view state in, one probability per view out) wrapped by
`ScoredPlanner`, which keeps the views above 0.5 as the paper does. Baselines:

- ``oracle``: the generator's exact label for this very case, what a perfect network trained on the
  dataset would predict;
- ``greedy`` / ``greedy:K``: next-best view by true new surface, one view at a time, until no view
  adds surface (or K views in all, the initial one included): the search-based NBV bound;
- ``random`` / ``random:K``: seeded uniform views, as many as the oracle's (or K in all);
- ``all``: every candidate view.

``osvp:FILE`` loads a checkpoint of the `osvp` training package through its ``osvp.planning`` module
(``load_scorer(path) -> ViewScorer``), imported only when asked for.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from datagen.errors import PlannerError
from datagen.evaluate.situation import Situation
from datagen.pipeline.setcover import mask_to_views

CHOICE_THRESHOLD = 0.5
"""A view is chosen when its probability exceeds this (the paper's rule)."""

PLANNER_HELP = "oracle, greedy, greedy:K, random, random:K, all or osvp:CHECKPOINT"


@dataclass(frozen=True)
class Plan:
    """A planner's answer: the views to take after the initial one."""

    views: tuple[int, ...]
    ordered: bool = False
    """True: visit in this order; False: a one-shot set, ordered by the shortest open path."""
    probabilities: npt.NDArray[np.float64] | None = None


class Planner(Protocol):
    name: str
    uses_refinement: bool
    """Whether the planner reads the refined input or the generator's label (the scene must be refined)."""

    def plan(self, situation: Situation) -> Plan: ...


class ViewScorer(Protocol):
    """A trained network: one probability per candidate view for a cloud and a view state.

    A scorer with ``source = "observed"`` gets what the input views saw (the paper's "Ours-Sparse");
    any other gets the refined cloud P(O_S), a shard's ``points``.
    """

    def view_probabilities(
        self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float64]: ...


class OraclePlanner:
    name = "oracle"
    uses_refinement = True

    def plan(self, situation: Situation) -> Plan:
        return Plan(views=mask_to_views(situation.oracle_label().label))


class AllPlanner:
    name = "all"
    uses_refinement = False

    def plan(self, situation: Situation) -> Plan:
        return Plan(views=tuple(v for v in range(situation.scene.num_views) if v != situation.initial_view))


class GreedyPlanner:
    """Next-best view by the true new surface each candidate would add; ties go to the lowest view id."""

    uses_refinement = False

    def __init__(self, total_views: int | None = None) -> None:
        self.total_views = total_views
        self.name = "greedy" if total_views is None else f"greedy:{total_views}"

    def plan(self, situation: Situation) -> Plan:
        scene = situation.scene
        seen = scene.seen([situation.initial_view])
        taken = [situation.initial_view]
        limit = scene.num_views if self.total_views is None else self.total_views
        while len(taken) < limit:
            gains = [
                -1 if v in taken else int(np.count_nonzero(~seen[scene.view_columns[v]]))
                for v in range(scene.num_views)
            ]
            best = int(np.argmax(gains))
            if gains[best] <= 0 and self.total_views is None:
                break
            if gains[best] < 0:
                break
            taken.append(best)
            seen[scene.view_columns[best]] = True
        return Plan(views=tuple(taken[1:]), ordered=True)


class RandomPlanner:
    """Uniform views other than the initial one, from the situation's own seeded stream."""

    def __init__(self, total_views: int | None = None) -> None:
        self.total_views = total_views
        self.name = "random" if total_views is None else f"random:{total_views}"
        self.uses_refinement = total_views is None

    def plan(self, situation: Situation) -> Plan:
        others = [v for v in range(situation.scene.num_views) if v != situation.initial_view]
        wanted = self.total_views - 1 if self.total_views is not None else situation.oracle_label().label.bit_count()
        count = min(wanted, len(others))
        chosen = situation.rng().choice(len(others), size=count, replace=False)
        return Plan(views=tuple(sorted(others[i] for i in chosen)))


class ScoredPlanner:
    """A trained network as a planner: the views whose probability exceeds 0.5, initial view excluded."""

    uses_refinement = True

    def __init__(self, name: str, scorer: ViewScorer) -> None:
        self.name = name
        self.scorer = scorer

    def plan(self, situation: Situation) -> Plan:
        request = situation.request()
        cloud = request.observed if getattr(self.scorer, "source", "points") == "observed" else request.points
        probabilities = np.asarray(self.scorer.view_probabilities(cloud, request.view_state), dtype=np.float64)
        if probabilities.shape != (request.num_views,):
            raise PlannerError(
                f"planner {self.name} returned {probabilities.shape} probabilities for {request.num_views} views; "
                "its checkpoint was trained for another view space"
            )
        chosen = tuple(
            int(v) for v in np.flatnonzero(probabilities > CHOICE_THRESHOLD) if int(v) != situation.initial_view
        )
        return Plan(views=chosen, probabilities=probabilities)


def load_osvp_scorer(path: Path) -> ViewScorer:
    """The `osvp` package's scorer for a checkpoint; imported here only, so datagen runs without it."""
    if not path.is_file():
        raise PlannerError(f"{path}: checkpoint not found; give the path of a file written by `osvp train`")
    try:
        module = importlib.import_module("osvp.planning")
    except ModuleNotFoundError as exc:
        if exc.name not in ("osvp", "osvp.planning"):
            raise  # osvp is there but one of its own dependencies is not: not this message
        raise PlannerError(
            f"planner osvp:{path} needs the osvp package; install it with `pip install ./osvp`"
        ) from None
    scorer: ViewScorer = module.load_scorer(path)
    return scorer


def make_planner(spec: str) -> Planner:
    """The planner a command-line name stands for; `PlannerError` names the choices otherwise."""
    name, colon, argument = spec.partition(":")
    if colon and not argument:
        raise PlannerError(f"planner {spec!r} names nothing after ':'; choose {PLANNER_HELP}")
    if name == "osvp" and argument:
        return ScoredPlanner(spec, load_osvp_scorer(Path(argument)))
    if name == "oracle" and not argument:
        return OraclePlanner()
    if name == "all" and not argument:
        return AllPlanner()
    if name in ("greedy", "random"):
        total = _view_count(spec, argument) if argument else None
        return GreedyPlanner(total) if name == "greedy" else RandomPlanner(total)
    raise PlannerError(f"unknown planner {spec!r}; choose {PLANNER_HELP}")


def _view_count(spec: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise PlannerError(f"planner {spec!r}: K must be a whole number of views >= 1 (the initial view counts)")
    return value
