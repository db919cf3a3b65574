"""Trained networks as planners, and the plug-ins that bring them.

A one-shot `schemas.planning.ViewScorer` is wrapped by `ScoredPlanner`, which keeps the views above
0.5 as the paper does, or lets a `DecodingScorer` turn the probabilities into views its own way. A
plug-in is the `ScorerFactory` an installed distribution registers as entry point NAME in the group
``datagen.planners`` (`PLANNER_ENTRY_POINTS`), imported only when asked for and called with ARG once
per process (`plugin_scorer`).
"""

from __future__ import annotations

from importlib.metadata import EntryPoint

import numpy as np
import numpy.typing as npt

from datagen.errors import DatagenError, PlannerError
from datagen.evaluate.grids import SceneGrids, empty_log_odds, inserted, occupancy_grid
from datagen.evaluate.protocol import Plan, one_line
from datagen.evaluate.situation import Situation
from schemas.planning import DecodingScorer, NextViewScorer, ScorerFactory, ViewScorer

CHOICE_THRESHOLD = 0.5
"""A view is chosen when its probability exceeds this (the paper's rule)."""


class ScoredPlanner:
    """A trained network as a planner: the views whose probability exceeds 0.5, or those its scorer's
    decoding selects (a `DecodingScorer`), the views already taken excluded."""

    uses_refinement = True

    def __init__(self, name: str, scorer: ViewScorer, decoding: str | None = None) -> None:
        _check_decoding(name, scorer, decoding)
        self.name = name
        self.scorer = scorer
        self.decoding = decoding
        """None: the scorer's default (the paper's 0.5 rule for a scorer without decodings)."""
        self.grids = SceneGrids() if getattr(scorer, "uses_grid", False) else None
        """A grid planner's (SCVP's manner) scene grids: it is shown the initial view's occupancy grid
        and the cloud that view observed, and needs no refinement."""
        self.uses_refinement = self.grids is None

    def plan(self, situation: Situation) -> Plan:
        if self.grids is None:
            request = situation.request()
            cloud = request.observed if getattr(self.scorer, "source", "points") == "observed" else request.points
            view_state = request.view_state
            scores = self.scorer.view_probabilities(cloud, view_state)
        else:
            view_state = np.zeros(situation.scene.num_views, dtype=np.float32)
            view_state[situation.initial_view] = 1.0
            cloud = situation.scene.observed_points([situation.initial_view])
            grid = occupancy_grid(inserted(empty_log_odds(), self.grids.of(situation), [situation.initial_view]))
            scores = self.scorer.view_probabilities(cloud, view_state, grid=grid)  # type: ignore[call-arg]
        probabilities = np.asarray(scores, dtype=np.float64)
        self._check_length("probabilities", probabilities, view_state.size)
        take = self._select(probabilities, view_state)
        open_views = np.asarray(view_state) == 0
        chosen = np.flatnonzero(take & open_views)
        ranking = tuple(int(v) for v in np.argsort(-probabilities, kind="stable") if open_views[v])
        return Plan(views=tuple(int(v) for v in chosen), probabilities=probabilities, at_count=lambda c: ranking[:c])

    def _select(
        self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.bool_]:
        if not isinstance(self.scorer, DecodingScorer):
            return probabilities > CHOICE_THRESHOLD
        try:
            take = np.asarray(self.scorer.select_views(probabilities, view_state, self.decoding), dtype=bool)
        except ValueError as exc:
            raise PlannerError(f"planner {self.name}: {exc}") from None
        self._check_length("view choices", take, probabilities.size)
        return take

    def _check_length(self, what: str, values: npt.NDArray[np.generic], num_views: int) -> None:
        if values.shape != (num_views,):
            raise PlannerError(
                f"planner {self.name} returned {values.shape} {what} for {num_views} views; "
                "its checkpoint was trained for another view space"
            )


def _check_decoding(name: str, scorer: ViewScorer, decoding: str | None) -> None:
    """Refuse a decoding the scorer cannot apply before any imaging (``threshold=0.3`` is checked as
    ``threshold``); a scorer that lists no ``decodings`` is asked when it plans."""
    if decoding is None:
        return
    if not isinstance(scorer, DecodingScorer):
        raise PlannerError(f"planner {name!r}: this scorer has no decodings; drop '+{decoding}' for its 0.5 rule")
    accepted = getattr(scorer, "decodings", None)
    if accepted is not None and decoding.partition("=")[0] not in accepted:
        raise PlannerError(f"planner {name!r}: unknown decoding {decoding!r}; choose {', '.join(accepted)}")


_SCORERS: dict[tuple[EntryPoint, str], ViewScorer | NextViewScorer] = {}
"""The scorers built in this process, by plugin and argument (`plugin_scorer`)."""


def plugin_scorer(plugin: EntryPoint, argument: str, spec: str) -> ViewScorer | NextViewScorer:
    """The scorer a planner plugin's factory builds for ARGUMENT (``spec`` names the planner in errors).

    Built once per process and plugin and argument, however many objects and situations ask (a
    checkpoint is read once, not once per object): a file changed under the same path in the same
    process is not read again. Every failure is one `PlannerError` line: a plugin that cannot be
    imported (naming its distribution), an argument its factory refuses (its `DatagenError` goes
    through as it is), or a factory that returns neither a `ViewScorer` nor a `NextViewScorer`.
    """
    key = (plugin, argument)
    if key not in _SCORERS:
        _SCORERS[key] = _build_scorer(plugin, argument, spec)
    return _SCORERS[key]


def _build_scorer(plugin: EntryPoint, argument: str, spec: str) -> ViewScorer | NextViewScorer:
    dist = plugin.dist
    source = f"distribution {dist.name} {dist.version}" if dist is not None else "its distribution"
    try:
        factory: ScorerFactory = plugin.load()
    except Exception as exc:  # any import-time failure of third-party code: one line, not a traceback
        raise PlannerError(
            f"planner plugin {plugin.name!r} ({plugin.value}, {source}) cannot be imported: {one_line(exc)}"
        ) from None
    try:
        scorer = factory(argument)
    except DatagenError:
        raise
    except (ValueError, OSError) as exc:
        raise PlannerError(f"planner {spec!r}: {one_line(exc, named=False)}") from None
    if not isinstance(scorer, ViewScorer | NextViewScorer):
        raise PlannerError(
            f"planner {spec!r}: plugin {plugin.name!r} ({plugin.value}, {source}) returned a "
            f"{type(scorer).__name__}, not a scorer with view_probabilities(points, view_state) or "
            "next_view_scores(observation)"
        )
    return scorer
