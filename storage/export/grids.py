"""The occupancy grid as the grid layouts (MA-SCVP, NBVNet) write it, and what their provenance says of it.

A case's grid comes from its shard's per-view ray cells (docs/pipeline.md section 8.2) in double, the
precision OctoMap reports and the authors' generator prints; the arrays hold the same values in
float32, exactly `storage.Dataset.next_view(i, grid=True).grid` flattened x-major.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from schemas.shard import GRID_HITS, GRID_MISSES
from storage.readers.reader import Dataset
from storage.samples.bits import bools_mask
from storage.samples.occupancy_grid import (
    GRID_CELLS,
    GRID_SIDE,
    HIT_LOG_ODDS,
    MAX_LOG_ODDS,
    MIN_LOG_ODDS,
    MISS_LOG_ODDS,
    case_probabilities,
)


class Grids:
    """Each sample's occupancy probabilities, read from its shard (each shard's arrays once)."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def of(self, i: int, view_state: npt.NDArray[np.bool_]) -> npt.NDArray[np.float64]:
        """(GRID_CELLS,) probabilities of sample i, whose view state is ``view_state`` (a bool per
        view), x-major: from its task's ray cells in double (the ``grid`` field's are float32)."""
        shard = self.dataset.shard(self.dataset.samples.shard(i))
        return case_probabilities(shard.array(GRID_HITS), shard.array(GRID_MISSES), bools_mask(view_state))


def grid_line(name: str) -> str:
    return (
        f"{name}: {GRID_SIDE}^3 occupancy probabilities, one per line in the authors' loop order (x, then y, "
        "then z: line (i x 32 + j) x 32 + k), printed as C++ prints a double (6 significant digits); the "
        "case's views inserted into an OctoMap-style grid in ascending view order with OctoMap's default updates "
        "(hit logodds(0.7), miss logodds(0.4), clamped to probabilities 0.1192 and 0.971, unknown 0.5: a cell "
        "hit once prints 0.7, missed twice 0.307692, as in theirs), centred on the object, half side 17/16 of its "
        "farthest ground-truth point, floor the higher of -half side and the table, as theirs; their rays run "
        "to each visible ground-truth voxel of a copy of the object with a table plane (the table shows as occupied "
        "cells at the floor), ours to the 2 mm visible keys V_i without a table; their cells lie on "
        "OctoMap's global grid (a sample point can read a cell up to one cell off), ours are the grid's own"
    )


def grid_facts() -> dict[str, Any]:
    return {
        "side": GRID_SIDE,
        "cells": GRID_CELLS,
        "order": "x-major: line/column (i * 32 + j) * 32 + k, as the authors' i, j, k loops",
        "values": "OctoMap occupancy probability 1 - 1/(1 + exp(log-odds)), log-odds in float32",
        "updates": {
            "hit": float(HIT_LOG_ODDS),
            "miss": float(MISS_LOG_ODDS),
            "clamp": [float(MIN_LOG_ODDS), float(MAX_LOG_ODDS)],
            "unknown": 0.5,
        },
        "text": "C++ ostream default for a double: 6 significant digits (printf %g)",
        "array": "float32, the same probabilities (storage Dataset.next_view(i, grid=True).grid, x-major)",
        "differs_from_authors": [
            "rays end at the visible 2 mm keys V_i, theirs at ground-truth voxels of a rendered copy",
            "no table plane (theirs shows the table as occupied cells at the floor)",
            "cells are the grid's own, theirs OctoMap's global cells read at the grid's sample points",
        ],
    }
