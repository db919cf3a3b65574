"""A case's 32^3 occupancy grid from a shard's per-view ray grids (docs/pipeline.md section 8.2).

A version-3 shard keeps, per view, which cells of the task's grid its rays end in (``grid_hits``)
and which they only cross (``grid_misses``), bit-packed. A case's grid is those views inserted one
after another in ascending view order, the way MA-SCVP's generator fills an OctoMap: each insertion
adds OctoMap's hit log-odds to the cells it ends in and its miss log-odds to the cells it crosses,
clamping after every update, in float32 as OctoMap stores them. Unknown cells stay at log-odds 0
(probability 0.5). Storing the view grids once per task, rather than one grid per sample, keeps a
sample's share to a few hundred bytes; the arithmetic is a few vector operations per view.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

GRID_SIDE = 32
"""Cells per axis of the planners' input grid (NBVNet, SCVP, MA-SCVP)."""
GRID_CELLS = GRID_SIDE**3
PACKED_CELLS = GRID_CELLS // 8
"""Bytes of one view's bit-packed cell set."""


def log_odds(probability: float) -> np.float32:
    """log(p / (1 - p)) as OctoMap stores it (a float)."""
    return np.float32(np.log(probability / (1.0 - probability)))


HIT_LOG_ODDS = log_odds(0.7)
"""OctoMap's default hit update, set as probability 0.7 (0.8473; its comments round it to 0.85)."""
MISS_LOG_ODDS = log_odds(0.4)
"""OctoMap's default miss update, probability 0.4 (-0.4055)."""
MIN_LOG_ODDS = log_odds(0.1192)
"""OctoMap's default lower clamp, probability 0.1192 (-2.00003)."""
MAX_LOG_ODDS = log_odds(0.971)
"""OctoMap's default upper clamp, probability 0.971 (3.5110)."""


def pack_cells(cells: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint8]:
    """(..., GRID_CELLS) bools -> (..., PACKED_CELLS) bytes, bit c % 8 of byte c // 8 is cell c."""
    return np.packbits(np.asarray(cells, dtype=bool), axis=-1, bitorder="little")


def unpack_cells(packed: npt.NDArray[np.uint8]) -> npt.NDArray[np.bool_]:
    """Inverse of `pack_cells`."""
    return np.unpackbits(np.asarray(packed, dtype=np.uint8), axis=-1, bitorder="little").astype(bool)


def case_log_odds(hits: npt.NDArray[np.uint8], misses: npt.NDArray[np.uint8], case: int) -> npt.NDArray[np.float32]:
    """(GRID_CELLS,) float32 log-odds of case ``case`` (a view mask) from the task's packed per-view
    ``hits`` and ``misses`` (n, PACKED_CELLS): its views inserted in ascending order."""
    value = np.zeros(GRID_CELLS, dtype=np.float32)
    view = 0
    remaining = int(case)
    while remaining:
        if remaining & 1:
            insert_view(value, hits[view], misses[view])
        remaining >>= 1
        view += 1
    return value


def insert_view(value: npt.NDArray[np.float32], hits: npt.NDArray[np.uint8], misses: npt.NDArray[np.uint8]) -> None:
    """Insert one view, given its packed ``hits`` and ``misses`` (PACKED_CELLS,), into the log-odds
    ``value`` in place: OctoMap's miss and hit updates, each clamped."""
    missed = unpack_cells(misses)
    value[missed] = np.maximum(value[missed] + MISS_LOG_ODDS, MIN_LOG_ODDS)
    hit = unpack_cells(hits)
    value[hit] = np.minimum(value[hit] + HIT_LOG_ODDS, MAX_LOG_ODDS)


def occupancy(log_odds: npt.NDArray[np.float32]) -> npt.NDArray[np.float64]:
    """OctoMap's occupancy probability of float32 log-odds, computed as it does (in double)."""
    return 1.0 - 1.0 / (1.0 + np.exp(np.asarray(log_odds, dtype=np.float64)))


def case_probabilities(
    hits: npt.NDArray[np.uint8], misses: npt.NDArray[np.uint8], case: int
) -> npt.NDArray[np.float64]:
    """(GRID_CELLS,) occupancy probabilities of a case in double, x-major: the values OctoMap reports and
    the authors' generator writes as text (`case_grid` is them in float32)."""
    return occupancy(case_log_odds(hits, misses, case))


def case_grid(hits: npt.NDArray[np.uint8], misses: npt.NDArray[np.uint8], case: int) -> npt.NDArray[np.float32]:
    """(32, 32, 32) float32 occupancy probabilities of a case, indexed [x, y, z] (0.5 unknown)."""
    return case_probabilities(hits, misses, case).astype(np.float32).reshape(GRID_SIDE, GRID_SIDE, GRID_SIDE)
