"""Next-best-view play: a scorer asked again after every view, as NBVNet and PCNBV are played.

`SequentialPlanner` starts from the initial view and, at every step, shows its scorer
(`schemas.planning.NextViewScorer`) what has been observed so far: the views taken, their view
state, the accumulated cloud and the case's occupancy grid (docs/pipeline.md section 8.2, the views
inserted in the order visited). It visits the open view of highest score (lowest index among
equals) until it holds its view count: K in all when one was asked for (``NAME:K`` or
``--budget-views K``, the paper's Table III), else `DEFAULT_TOTAL_VIEWS` (its Table II), or until
every open view scores 0 or less with no count asked for (the scorer says nothing is left).

The built-in ``gain`` scorer returns every view's true new surface (`TrueGains`), which makes the
play the ``greedy`` bound, view for view.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from datagen.errors import PlannerError
from datagen.evaluate.grids import SceneGrids, empty_log_odds, inserted, occupancy_grid
from datagen.evaluate.protocol import Plan, one_line
from datagen.evaluate.scene import Scene
from datagen.evaluate.situation import Situation
from schemas.planning import NextViewObservation, NextViewScorer

DEFAULT_TOTAL_VIEWS = 10
"""Views in all (the initial one included) when no count is asked for: NBVNet's and PCNBV's 10 iterations."""


class TrueGains:
    """The scorer that knows the object: each view's keys that the views taken have not seen."""

    uses_grid = False

    def __init__(self, scene: Scene) -> None:
        self.scene = scene

    def next_view_scores(self, observation: NextViewObservation) -> npt.NDArray[np.float64]:
        seen = self.scene.seen(observation.views)
        return np.array([np.count_nonzero(~seen[c]) for c in self.scene.view_columns], dtype=np.float64)


ScorerFor = Callable[[Situation], NextViewScorer]
"""The scorer of one situation (a plugin's is the same for all; `TrueGains` is the scene's)."""


@dataclass
class SequentialPlanner:
    """Next-best-view play with ``scorer_for``'s scorer; ``total_views`` in all when asked for."""

    name: str
    scorer_for: ScorerFor
    total_views: int | None = None
    uses_refinement = False
    grids: SceneGrids = field(default_factory=SceneGrids)

    def plan(self, situation: Situation) -> Plan:
        scene = situation.scene
        scorer = self.scorer_for(situation)
        grids = self.grids.of(situation) if getattr(scorer, "uses_grid", True) else None
        taken = [situation.initial_view]
        log_odds = inserted(empty_log_odds(), grids, taken) if grids is not None else empty_log_odds()
        limit = min(self.total_views or DEFAULT_TOTAL_VIEWS, scene.num_views)
        while len(taken) < limit:
            scores = self._scores(scorer, scene, taken, log_odds if grids is not None else None)
            open_views = np.ones(scene.num_views, dtype=bool)
            open_views[taken] = False
            candidates = np.where(open_views, scores, -np.inf)
            best = int(np.argmax(candidates))
            if candidates[best] <= 0 and self.total_views is None:
                break
            taken.append(best)
            if grids is not None:
                log_odds = inserted(log_odds, grids, [best])
        return Plan(views=tuple(taken[1:]), ordered=True)

    def _scores(
        self, scorer: NextViewScorer, scene: Scene, taken: list[int], log_odds: npt.NDArray[np.float32] | None
    ) -> npt.NDArray[np.float64]:
        state = np.zeros(scene.num_views, dtype=np.float32)
        state[taken] = 1.0
        grid = occupancy_grid(log_odds) if log_odds is not None else None
        observation = NextViewObservation(
            views=tuple(taken), view_state=state, cloud=scene.observed_points(taken), grid=grid
        )
        step = len(taken)
        try:
            scores = np.asarray(scorer.next_view_scores(observation), dtype=np.float64)
        except Exception as exc:
            raise PlannerError(
                f"planner {self.name} failed at step {step} (after views {', '.join(map(str, taken))}): {one_line(exc)}"
            ) from None
        if scores.shape != (scene.num_views,) or not np.isfinite(scores).all():
            raise PlannerError(
                f"planner {self.name} returned {scores.shape} scores at step {step} for {scene.num_views} views "
                "(one finite score per view); its checkpoint was trained for another view space"
            )
        return scores
