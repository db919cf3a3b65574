"""The planners' 32^3 occupancy grid: each view's rays walked through it (docs/pipeline.md section 8.2).

The grid is MA-SCVP's: centred on the object (the frame's origin, where every view looks), half a
side of 17/16 of the largest distance from the centre to a P_gt point, its floor raised to the table
(one voxel below the lowest P_gt point) when that is higher. A view's cloud is the centres of the
keys it sees (V_i); each point's ray from the view's camera centre ends in one cell (a hit) and
crosses others (misses, minus that view's hits, as OctoMap discretises one insertion). The walk is an
exact voxel traversal (Amanatides and Woo), all rays of all views advanced together in numpy.
`storage.samples.occupancy_grid` turns a case's views into its log-odds grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.keys import key_centres, unpack_keys
from storage.samples import GRID_CELLS, GRID_SIDE, pack_cells

RADIUS_MARGIN = 17.0 / 16.0
"""MA-SCVP's grid half-side over the object's radius."""


@dataclass(frozen=True)
class GridFrame:
    """Where the grid lies in the task frame: cell (i, j, k) spans ``corner + cell * [i, i+1)`` etc."""

    corner: tuple[float, float, float]
    cell: float

    def as_array(self) -> npt.NDArray[np.float64]:
        """(4,) float64: corner x, y, z and the cell size, metres (a shard's ``grid_frame``)."""
        return np.array([*self.corner, self.cell], dtype=np.float64)


@dataclass(frozen=True)
class ViewGrids:
    """Every view's ray cells in the task's grid, bit-packed (`storage.samples.pack_cells`)."""

    frame: GridFrame
    hits: npt.NDArray[np.uint8]
    """(n, GRID_CELLS / 8): cells a view's rays end in."""
    misses: npt.NDArray[np.uint8]
    """(n, GRID_CELLS / 8): cells they cross and do not end in."""


def grid_frame(ground_truth_centres: npt.NDArray[np.floating], voxel_size: float) -> GridFrame:
    """The grid of an object whose P_gt key centres (G, 3) are given, in the task frame."""
    points = np.asarray(ground_truth_centres, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        raise ValueError("an occupancy grid needs P_gt points")
    half = RADIUS_MARGIN * float(np.sqrt((points**2).sum(axis=1)).max())
    table = float(points[:, 2].min()) - voxel_size
    return GridFrame(corner=(-half, -half, max(table, -half)), cell=2.0 * half / GRID_SIDE)


def view_grids(
    visible: Sequence[npt.NDArray[np.int64]],
    ground_truth: npt.NDArray[np.int64],
    positions: npt.NDArray[np.float64],
    voxel_size: float,
    grid_offset: Sequence[float],
) -> ViewGrids:
    """Each view's hit and miss cells, from its packed visible keys V_i and its camera position."""
    frame = grid_frame(key_centres(unpack_keys(ground_truth), voxel_size, grid_offset), voxel_size)
    views = len(visible)
    counts = np.array([keys.size for keys in visible], dtype=np.int64)
    ends = key_centres(unpack_keys(np.concatenate(list(visible))), voxel_size, grid_offset)
    starts = np.repeat(np.asarray(positions, dtype=np.float64).reshape(-1, 3), counts, axis=0)
    owner = np.repeat(np.arange(views, dtype=np.int64), counts)
    hit_cells, misses = walk_rays(starts, ends, frame, owner, views)
    hits = np.zeros((views, GRID_CELLS), dtype=bool)
    inside = hit_cells >= 0
    hits[owner[inside], hit_cells[inside]] = True
    misses &= ~hits
    return ViewGrids(frame=frame, hits=pack_cells(hits), misses=pack_cells(misses))


def cell_index(cell: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Flat index of (..., 3) cells in the authors' order (x slowest, z fastest)."""
    return (cell[..., 0] * GRID_SIDE + cell[..., 1]) * GRID_SIDE + cell[..., 2]


def walk_rays(
    starts: npt.NDArray[np.floating],
    ends: npt.NDArray[np.floating],
    frame: GridFrame,
    groups: npt.NDArray[np.int64],
    count: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """For segments ``starts -> ends`` (R, 3) in ``groups`` (R,) of ``count``: the flat cell each ends
    in (-1 outside the grid), and per group (count, GRID_CELLS) the grid cells its segments pass
    through before their end cells."""
    corner = np.asarray(frame.corner, dtype=np.float64)
    origin = (starts - corner) / frame.cell
    target = (ends - corner) / frame.cell
    end_cell = np.floor(target).astype(np.int64)
    end_inside = np.all((end_cell >= 0) & (end_cell < GRID_SIDE), axis=1)
    end_flat = np.where(end_inside, cell_index(np.clip(end_cell, 0, GRID_SIDE - 1)), -1)

    direction = target - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / direction
        t_low = (0.0 - origin) * inverse
        t_high = (GRID_SIDE - origin) * inverse
    moving = direction != 0
    still_inside = (origin >= 0) & (origin < GRID_SIDE)
    t_in = np.where(moving, np.minimum(t_low, t_high), np.where(still_inside, -np.inf, np.inf))
    t_out = np.where(moving, np.maximum(t_low, t_high), np.where(still_inside, np.inf, -np.inf))
    enter = np.maximum(t_in.max(axis=1), 0.0)
    leave = np.minimum(t_out.min(axis=1), 1.0)
    active = np.flatnonzero(enter < leave)

    point = origin[active] + enter[active, None] * direction[active]
    cell = np.clip(np.floor(point).astype(np.int64), 0, GRID_SIDE - 1)
    step = np.sign(direction[active]).astype(np.int64)
    boundary = cell + (step > 0)
    with np.errstate(invalid="ignore"):
        t_next = np.where(moving[active], (boundary - origin[active]) * inverse[active], np.inf)
    t_delta = np.where(moving[active], np.abs(inverse[active]), np.inf)
    flat = cell_index(cell)
    goal = end_flat[active]
    stride = np.array([GRID_SIDE * GRID_SIDE, GRID_SIDE, 1], dtype=np.int64)

    crossed = np.zeros((count, GRID_CELLS), dtype=bool)
    group = groups[active]
    for _ in range(3 * GRID_SIDE + 3):
        if active.size == 0:
            break
        keep = flat != goal
        crossed[group[keep], flat[keep]] = True
        # The axis whose boundary comes first; equal times go to the later axis, as OctoMap's walk does.
        t_x, t_y, t_z = t_next[:, 0], t_next[:, 1], t_next[:, 2]
        axis = np.where(t_x < t_y, np.where(t_x < t_z, 0, 2), np.where(t_y < t_z, 1, 2))
        at = np.arange(active.size) * 3 + axis
        crossing = t_next.ravel()[at]
        moved = step.ravel()[at]
        coordinate = cell.ravel()[at] + moved
        cell.ravel()[at] = coordinate
        t_next.ravel()[at] = crossing + t_delta.ravel()[at]
        flat += moved * stride[axis]
        go = keep & (crossing <= 1.0) & (coordinate >= 0) & (coordinate < GRID_SIDE)
        active, group, cell, step, t_next, t_delta, flat, goal = (
            active[go],
            group[go],
            cell[go],
            step[go],
            t_next[go],
            t_delta[go],
            flat[go],
            goal[go],
        )
    return end_flat, crossed
