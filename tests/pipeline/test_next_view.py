"""The next-view labels (docs/pipeline.md sections 8.1-8.2): every view's gains and the best next view
against a brute-force count on the built-ins, the occupancy grid's ray walk against an independent
per-cell segment test on a box with known free, occupied and unknown cells, OctoMap's clamped
log-odds against a scalar replay, and the damage `datagen shards validate` names."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from support import storage as fx

from datagen.inspection.label_check import check_labels
from datagen.pipeline.keys import key_centres, pack_keys, unpack_keys
from datagen.pipeline.occupancy import GridFrame, view_grids, walk_rays
from schemas.shard import GRID_HITS, VIEW_GAINS
from storage import open_dataset, validate
from storage.readers import load_memory
from storage.samples import (
    GRID_CELLS,
    GRID_SIDE,
    HIT_LOG_ODDS,
    MAX_LOG_ODDS,
    MIN_LOG_ODDS,
    MISS_LOG_ODDS,
    case_log_odds,
    occupancy,
    pack_cells,
    unpack_cells,
)

VOXEL = 0.002
OFFSET = (0.2718, 0.3141, 0.1618)


# ---------------------------------------------------------------------------------------------------------
# gains and best views: brute force over Python sets
# ---------------------------------------------------------------------------------------------------------


def brute_gains(result, case: int, alpha: int) -> tuple[list[int], list[int], int]:  # type: ignore[no-untyped-def]
    visible = [set(v.tolist()) for v in result.sets.visible]
    refined = [set(p.tolist()) for p in result.sets.refined]
    every = set().union(*refined)
    full = {k for k in every if sum(k in p for p in refined) >= alpha}
    coverage = [p & full for p in refined]
    views = range(len(visible))
    seen = set().union(*(visible[v] for v in views if case >> v & 1))
    covered = set().union(*(coverage[v] for v in views if case >> v & 1))
    gains = [0 if case >> v & 1 else len(visible[v] - seen) for v in views]
    coverage_gains = [0 if case >> v & 1 else len(coverage[v] - covered) for v in views]
    best, best_gain = -1, -1
    for v in views:
        if not case >> v & 1 and gains[v] > best_gain:
            best, best_gain = v, gains[v]
    return gains, coverage_gains, best


def test_gains_and_best_views_match_a_brute_force_count_on_the_built_ins() -> None:
    alpha = fx.config().alpha
    checked = 0
    for result in fx.task_results():
        union = set().union(*(set(v.tolist()) for v in result.sets.visible))
        assert result.visible_size == len(union)
        for sample in result.samples:
            gains, coverage_gains, best = brute_gains(result, sample.case, alpha)
            assert sample.gains.visible.tolist() == gains, sample.sample_id
            assert sample.gains.coverage.tolist() == coverage_gains, sample.sample_id
            assert sample.gains.best_view == best, sample.sample_id
            top = max(g for v, g in enumerate(gains) if not sample.case >> v & 1)
            ties = sum(1 for v, g in enumerate(gains) if not sample.case >> v & 1 and g == top)
            assert sample.gains.best_view_ties == ties
            checked += 1
    assert checked > 50


def test_readers_serve_the_normalised_gains_and_the_best_view(tmp_path: Path) -> None:
    fx.build_dataset(str(tmp_path / "ds"), finalise_index=True)
    dataset = open_dataset(str(tmp_path / "ds"))
    memory = load_memory(dataset, fields=("grid",))
    batch = memory.batch(np.arange(len(memory)), 64, 0, 0)
    computed = {s.sample_id: (r, s) for r in fx.task_results() for s in r.samples}
    ids = dataset.index.column("sample_id").to_pylist()
    best = dataset.index.column("best_view").to_pylist()
    for row in range(len(memory)):
        result, sample = computed[ids[row]]
        np.testing.assert_allclose(batch.view_gain[row], sample.gains.visible / result.visible_size, rtol=1e-6)
        np.testing.assert_allclose(batch.coverage_gain[row], sample.gains.coverage / sample.full_size, rtol=1e-6)
        assert batch.best_view[row] == sample.gains.best_view == best[row]
        grid = batch.grid[row]
        assert grid.shape == (GRID_SIDE,) * 3 and 0.0 < grid.min() <= 0.5 <= grid.max() < 1.0
        if row % 7 == 0:  # held as per-task ray cells, built per batch: the reader's grid of the sample
            assert np.array_equal(grid, dataset.next_view(row, grid=True).grid)
    assert memory.grids is not None and "grid" not in memory.fields
    assert memory.grids.hits.nbytes + memory.grids.misses.nbytes < len(memory) * GRID_SIDE**3 * 4 / 8
    with pytest.raises(ValueError, match="'voxels' is no sample field"):
        load_memory(dataset, fields=("voxels",))


# ---------------------------------------------------------------------------------------------------------
# the grid: a box with known cells, and an independent segment-against-cell test
# ---------------------------------------------------------------------------------------------------------


def box_keys(half: float, top: float, bottom: float) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(the keys of a box's top face, the keys of its whole surface) for a box |x|, |y| <= half, z in
    [bottom, top], sampled finely."""
    ticks = np.arange(-half, half + 1e-9, VOXEL / 2)
    xs, ys = np.meshgrid(ticks, ticks, indexing="ij")
    top_face = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, top)])
    heights = np.arange(bottom, top + 1e-9, VOXEL / 2)
    sides = []
    for z in heights:
        for sign in (-1.0, 1.0):
            sides.append(np.column_stack([np.full(ticks.size, sign * half), ticks, np.full(ticks.size, z)]))
            sides.append(np.column_stack([ticks, np.full(ticks.size, sign * half), np.full(ticks.size, z)]))
    bottom_face = top_face.copy()
    bottom_face[:, 2] = bottom
    surface = np.concatenate([top_face, bottom_face, *sides])

    def keys(points: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
        return np.unique(pack_keys(np.floor(points / VOXEL + np.asarray(OFFSET)).astype(np.int64)))

    return keys(top_face), keys(surface)


def cells_crossed(start: npt.NDArray[np.float64], end: npt.NDArray[np.float64], frame: GridFrame) -> set[int]:
    """Every cell whose box the segment passes through, by a slab test of the segment against all
    32^3 cells (independent of the walk), minus the cell holding the end point."""
    corner = np.asarray(frame.corner)
    ijk = np.stack(np.meshgrid(*(np.arange(GRID_SIDE),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    low = corner + ijk * frame.cell
    high = low + frame.cell
    direction = end - start
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (low - start) / direction
        t2 = (high - start) / direction
    parallel = direction == 0
    inside = (start >= low) & (start < high)
    t_min = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    t_max = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    hit = np.maximum(t_min, 0.0) < np.minimum(t_max, 1.0)
    end_cell = np.floor((end - corner) / frame.cell).astype(np.int64)
    flat = (ijk[:, 0] * GRID_SIDE + ijk[:, 1]) * GRID_SIDE + ijk[:, 2]
    end_flat = (end_cell[0] * GRID_SIDE + end_cell[1]) * GRID_SIDE + end_cell[2]
    return set(flat[hit].tolist()) - {int(end_flat)}


def test_each_ray_crosses_exactly_the_cells_an_independent_segment_test_finds() -> None:
    rng = np.random.default_rng(7)
    frame = GridFrame(corner=(-0.08, -0.08, -0.05), cell=0.005)
    starts = rng.normal(size=(60, 3))
    starts = 0.4 * starts / np.linalg.norm(starts, axis=1, keepdims=True)
    starts[:, 2] = np.abs(starts[:, 2])
    ends = rng.uniform([-0.07, -0.07, -0.04], [0.07, 0.07, 0.09], size=(60, 3))
    end_cells, crossed = walk_rays(starts, ends, frame, np.arange(60), 60)
    for ray in range(60):
        walked = set(np.flatnonzero(crossed[ray]).tolist())
        assert walked == cells_crossed(starts[ray], ends[ray], frame), ray
        expected_end = np.floor((ends[ray] - np.asarray(frame.corner)) / frame.cell).astype(int)
        assert end_cells[ray] == (expected_end[0] * GRID_SIDE + expected_end[1]) * GRID_SIDE + expected_end[2]


def test_a_box_seen_from_above_has_known_free_occupied_and_unknown_cells() -> None:
    top_keys, surface = box_keys(half=0.03, top=0.02, bottom=-0.02)
    positions = np.array([[0.0, 0.0, 0.4], [0.4, 0.0, 0.0]])
    side_keys = surface[key_centres(unpack_keys(surface), VOXEL, OFFSET)[:, 0] > 0.029]
    grids = view_grids([top_keys, side_keys], surface, positions, VOXEL, OFFSET)
    frame = grids.frame
    centres = key_centres(unpack_keys(surface), VOXEL, OFFSET)
    radius = np.sqrt((centres**2).sum(axis=1)).max()
    assert frame.cell == pytest.approx(2 * 17 / 16 * radius / 32)
    assert frame.corner[2] == pytest.approx(max(centres[:, 2].min() - VOXEL, -17 / 16 * radius))

    hits, misses = unpack_cells(grids.hits), unpack_cells(grids.misses)
    corner = np.asarray(frame.corner)
    top_points = key_centres(unpack_keys(top_keys), VOXEL, OFFSET)
    top_cells = np.floor((top_points - corner) / frame.cell).astype(np.int64)
    expected_hits = np.zeros(GRID_CELLS, dtype=bool)
    expected_hits[(top_cells[:, 0] * GRID_SIDE + top_cells[:, 1]) * GRID_SIDE + top_cells[:, 2]] = True
    np.testing.assert_array_equal(hits[0], expected_hits)

    cell_centres = corner + (np.stack(np.meshgrid(*(np.arange(GRID_SIDE),) * 3, indexing="ij"), -1) + 0.5) * frame.cell
    cell_centres = cell_centres.reshape(-1, 3)
    inner = np.all(np.abs(cell_centres[:, :2]) < 0.025, axis=1)
    above = inner & (cell_centres[:, 2] > 0.02 + frame.cell)
    below = inner & (cell_centres[:, 2] < 0.02 - frame.cell)
    assert misses[0][above].all(), "the column above the top face is free"
    assert not (hits[0] | misses[0])[below].any(), "inside the box stays unknown for the top view"
    assert not (hits[0] & misses[0]).any() and not (hits[1] & misses[1]).any()
    # the side view sees x = +half: cells beyond it (x > half + a cell) on its rays are free, the far side unknown
    far = inner & (cell_centres[:, 0] < -0.01)
    assert not (hits[1] | misses[1])[far].any()
    # every ray of both views crosses the cells the independent test finds (summed per view)
    for view, (keys, position) in enumerate(zip([top_keys, side_keys], positions, strict=True)):
        ends = key_centres(unpack_keys(keys), VOXEL, OFFSET)
        crossed: set[int] = set()
        for end in ends[:: max(1, len(ends) // 40)]:
            crossed |= cells_crossed(position, end, frame)
        assert crossed <= set(np.flatnonzero(misses[view] | hits[view]).tolist())


def test_log_odds_replay_octomaps_clamped_updates_in_view_order() -> None:
    rng = np.random.default_rng(3)
    views = 6
    hit_cells = rng.random((views, GRID_CELLS)) < 0.3
    miss_cells = (rng.random((views, GRID_CELLS)) < 0.5) & ~hit_cells
    hits, misses = pack_cells(hit_cells), pack_cells(miss_cells)
    for case in (0b1, 0b101, 0b111111, 0b110110):
        got = case_log_odds(hits, misses, case)
        for cell in rng.choice(GRID_CELLS, size=200, replace=False).tolist():
            value = np.float32(0.0)
            for view in range(views):
                if case >> view & 1:
                    if miss_cells[view, cell]:
                        value = max(np.float32(value + MISS_LOG_ODDS), MIN_LOG_ODDS)
                    if hit_cells[view, cell]:
                        value = min(np.float32(value + HIT_LOG_ODDS), MAX_LOG_ODDS)
            assert got[cell] == value
    saturated = case_log_odds(
        pack_cells(np.ones((views, GRID_CELLS), bool)), pack_cells(np.zeros((views, GRID_CELLS), bool)), 0b111111
    )
    assert (saturated == MAX_LOG_ODDS).all()
    assert occupancy(np.float32(0.0)) == 0.5 and occupancy(MAX_LOG_ODDS) == pytest.approx(0.971, abs=1e-6)


def test_one_and_two_updates_print_what_the_authors_grid_holds() -> None:
    """OctoMap's defaults (hit probability 0.7, miss 0.4) printed as the authors' generator prints a
    double: the only values of the grid file in MA-SCVP's Demo (a two-view case) are 0.5 (unknown),
    0.4 (one miss), 0.307692 (two), 0.7 (one hit), 0.844828 (two) and 0.608696 (a miss, then a hit)."""
    one = np.ones((1, GRID_CELLS), dtype=bool)
    none = np.zeros((1, GRID_CELLS), dtype=bool)
    hit, miss = (pack_cells(one), pack_cells(none)), (pack_cells(none), pack_cells(one))
    sequences = {"0.4": [miss], "0.307692": [miss, miss], "0.7": [hit], "0.844828": [hit, hit], "0.608696": [miss, hit]}
    for printed, updates in sequences.items():
        hits = np.concatenate([h for h, _ in updates])
        misses = np.concatenate([m for _, m in updates])
        value = occupancy(case_log_odds(hits, misses, (1 << len(updates)) - 1))
        assert {f"{v:.6g}" for v in value.tolist()} == {printed}, printed


# ---------------------------------------------------------------------------------------------------------
# damage: storage recounts the gains, --all walks the grid again
# ---------------------------------------------------------------------------------------------------------


def edit(shard: str, name: str, change) -> None:  # type: ignore[no-untyped-def]
    fx.edit_array(Path(shard), name, change)


def test_validate_names_a_wrong_gain_and_all_names_a_wrong_grid(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    fx.build_dataset(str(root), finalise_index=True)
    assert validate(str(root), full=True) == [] and check_labels(str(root), full=True).problems == []
    shard = sorted(glob.glob(str(root / "shards" / "*" / "*.zarr.zip")))[0]
    relative = str(Path(shard).relative_to(root))

    def bump(values: np.ndarray) -> np.ndarray:
        values[2, 5] += 1
        return values

    def flip(values: np.ndarray) -> np.ndarray:
        values[3, 100] ^= 1
        return values

    edit(shard, VIEW_GAINS, bump)
    edit(shard, GRID_HITS, flip)
    assert f"{relative} row 2: {VIEW_GAINS} differ from the gains recounted from the stored sets" in validate(
        str(root), full=True
    )
    lines = [p.line for p in check_labels(str(root), full=True).problems]
    assert f"{relative}: {GRID_HITS} differs from the ray walk over the stored V_i and P_gt" in lines
