"""The occupancy grid a planner sees in ``datagen evaluate``: the views taken so far, inserted in order.

The grid is the one the generator stores for a case (docs/pipeline.md section 8.2): every view's
rays are walked once per scene through the task's 32^3 grid (`datagen.pipeline.occupancy`), and a
case's grid is its views inserted one after another with OctoMap's clamped updates
(`storage.samples.occupancy_grid`). A next-best-view planner inserts the views in the order it visits them; a
one-shot grid planner sees the grid of its initial view, as a training sample of that case holds.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from datagen.evaluate.scene import Scene
from datagen.evaluate.situation import Situation
from datagen.pipeline.occupancy import ViewGrids, view_grids
from storage.samples import GRID_CELLS, GRID_SIDE, insert_view, occupancy


class SceneGrids:
    """Every view's ray cells of a scene's grid, walked on the first use and kept for that scene."""

    def __init__(self) -> None:
        self._walked: tuple[Scene, ViewGrids] | None = None

    def of(self, situation: Situation) -> ViewGrids:
        scene = situation.scene
        if self._walked is None or self._walked[0] is not scene:
            config = situation.config
            visible = [o.keys for o in scene.scan.observations]
            walked = view_grids(
                visible, scene.scan.ground_truth.keys, scene.positions, config.voxel_size, config.grid_offset
            )
            self._walked = (scene, walked)
        return self._walked[1]


def empty_log_odds() -> npt.NDArray[np.float32]:
    """Every cell unknown (log-odds 0, probability 0.5)."""
    return np.zeros(GRID_CELLS, dtype=np.float32)


def inserted(log_odds: npt.NDArray[np.float32], grids: ViewGrids, views: Iterable[int]) -> npt.NDArray[np.float32]:
    """A copy of ``log_odds`` with ``views`` inserted in the order given (OctoMap's clamped updates)."""
    value = log_odds.copy()
    for view in views:
        insert_view(value, grids.hits[view], grids.misses[view])
    return value


def occupancy_grid(log_odds: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """(32, 32, 32) float32 occupancy probabilities indexed [x, y, z], as a sample's ``grid`` field."""
    return occupancy(log_odds).astype(np.float32).reshape(GRID_SIDE, GRID_SIDE, GRID_SIDE)
