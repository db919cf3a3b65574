"""The planner seam: what a trained view planner gives ``datagen evaluate``, and how it is found.

Both sides import this module and nothing of each other: ``datagen.evaluate.planners`` calls a
`ViewScorer`, a training package (``osvp``) provides one. Typing and numpy only, so a planner
package depends on ``schemas`` alone for it.

A planner package registers a `ScorerFactory` in the entry-point group `PLANNER_ENTRY_POINTS`::

    [project.entry-points."datagen.planners"]
    osvp = "osvp.planning:load_scorer"

A factory returns one of two kinds of planner, told apart by the method it has: a one-shot
`ViewScorer` (``view_probabilities``: a cloud and view state in, one probability per view out; its
views are taken at once) or a next-best-view `NextViewScorer` (``next_view_scores``: asked again after
every view with what has been observed so far, its best unvisited view is visited next).

``datagen evaluate --planner NAME:ARG`` (or ``NAME+DECODING:ARG``) then calls the factory of entry
point NAME with ARG, the text after the first ``:`` (a checkpoint path, say), once per process, and
plans with the scorer it returns. NAME must not be a built-in planner (oracle, greedy, random, all).
A factory raises a `schemas.errors.DatagenError` (or `ValueError`/`OSError`) with a one-line message
for an argument it cannot use (a missing or damaged checkpoint); ``datagen`` prints it as one error line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

__all__ = [
    "PLANNER_ENTRY_POINTS",
    "DecodingScorer",
    "NextViewObservation",
    "NextViewScorer",
    "ScorerFactory",
    "ViewScorer",
]

PLANNER_ENTRY_POINTS = "datagen.planners"
"""The entry-point group a planner package registers its `ScorerFactory` in, under the planner's NAME."""


@runtime_checkable
class ViewScorer(Protocol):
    """A trained network: one probability per candidate view for a cloud and a view state.

    ``points`` is an (N, 3) float32 cloud in metres; ``view_state`` holds one float32 per candidate
    view, 1 for the views already taken; the answer is one probability in [0, 1] per view, float64.
    The views above 0.5 are taken (the paper's rule) unless the scorer is a `DecodingScorer`.

    A scorer with ``source = "observed"`` gets what the input views saw (the paper's "Ours-Sparse");
    any other gets the refined cloud P(O_S), a shard's ``points``. A scorer with ``uses_grid = True``
    (SCVP's manner) is called with the keyword ``grid`` too: the (32, 32, 32) occupancy probabilities
    of its input views, as a sample's ``grid`` holds them; it gets the observed cloud, unrefined.
    """

    def view_probabilities(
        self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float64]: ...


@runtime_checkable
class DecodingScorer(ViewScorer, Protocol):
    """A scorer that decides itself which views its probabilities stand for (``NAME+DECODING:ARG``).

    ``decoding`` is None for the scorer's default, else the text between ``+`` and ``:``; an unknown
    one raises ``ValueError``. A scorer may also list the names it accepts as ``decodings`` (a tuple of
    str), so a bad name stops before any imaging; a parametrised decoding (``threshold=0.3``) is
    checked by the part before ``=``.
    """

    def select_views(
        self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32], decoding: str | None
    ) -> npt.NDArray[np.bool_]:
        """One bool per view, True = take it (the views already taken are dropped afterwards)."""
        ...


@dataclass(frozen=True)
class NextViewObservation:
    """What a next-best-view planner has observed after the views taken so far (the initial one first)."""

    views: tuple[int, ...]
    """The views taken, in the order visited."""
    view_state: npt.NDArray[np.float32]
    """(n,) 1 for the views taken."""
    cloud: npt.NDArray[np.float32]
    """(N, 3) the accumulated cloud: every surface point the views taken hit, metres, task frame."""
    grid: npt.NDArray[np.float32] | None
    """(32, 32, 32) occupancy probabilities of the views taken, indexed [x, y, z], 0.5 unknown
    (docs/pipeline.md section 8.2); None for a scorer whose ``uses_grid`` is False."""


@runtime_checkable
class NextViewScorer(Protocol):
    """A next-best-view network (PCNBV, NBVNet and the like), asked after every view.

    ``next_view_scores`` gives one score per candidate view, higher is better (a predicted gain or a
    class probability). The open view with the highest score is visited next, the lowest index among
    equals; when every open view scores 0 or less the scorer says nothing is left, and play stops
    unless a view count was asked for. A scorer that reads no grid may set ``uses_grid = False`` to
    spare building it.
    """

    def next_view_scores(self, observation: NextViewObservation) -> npt.NDArray[np.float64]: ...


ScorerFactory = Callable[[str], ViewScorer | NextViewScorer]
"""What a ``datagen.planners`` entry point loads: ARG of ``--planner NAME:ARG`` in, a scorer out."""
