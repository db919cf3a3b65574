"""The planner seam: what a trained view planner gives ``datagen evaluate``, and how it is found.

Both sides import this module and nothing of each other: ``datagen.evaluate.planners`` calls a
`ViewScorer`, a training package (``osvp``) provides one. Typing and numpy only, so a planner
package depends on ``schemas`` alone for it.

A planner package registers a `ScorerFactory` in the entry-point group `PLANNER_ENTRY_POINTS`::

    [project.entry-points."datagen.planners"]
    osvp = "osvp.planning:load_scorer"

``datagen evaluate --planner NAME:ARG`` (or ``NAME+DECODING:ARG``) then calls the factory of entry
point NAME with ARG, the text after the first ``:`` (a checkpoint path, say), once per process, and
plans with the scorer it returns. NAME must not be a built-in planner (oracle, greedy, random, all).
A factory raises a `schemas.errors.DatagenError` (or `ValueError`/`OSError`) with a one-line message
for an argument it cannot use (a missing or damaged checkpoint); ``datagen`` prints it as one error line.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

__all__ = ["PLANNER_ENTRY_POINTS", "DecodingScorer", "ScorerFactory", "ViewScorer"]

PLANNER_ENTRY_POINTS = "datagen.planners"
"""The entry-point group a planner package registers its `ScorerFactory` in, under the planner's NAME."""


@runtime_checkable
class ViewScorer(Protocol):
    """A trained network: one probability per candidate view for a cloud and a view state.

    ``points`` is an (N, 3) float32 cloud in metres; ``view_state`` holds one float32 per candidate
    view, 1 for the views already taken; the answer is one probability in [0, 1] per view, float64.
    The views above 0.5 are taken (the paper's rule) unless the scorer is a `DecodingScorer`.

    A scorer with ``source = "observed"`` gets what the input views saw (the paper's "Ours-Sparse");
    any other gets the refined cloud P(O_S), a shard's ``points``.
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


ScorerFactory = Callable[[str], ViewScorer]
"""What a ``datagen.planners`` entry point loads: ARG of ``--planner NAME:ARG`` in, a scorer out."""
