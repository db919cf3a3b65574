"""Turn a `TaskResult` (pipeline) into a `ShardPayload` (storage): the one place both meet."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from datagen.pipeline.keys import keys_to_int16, unpack_keys
from datagen.pipeline.task import TaskResult
from schemas.config import GenerationConfig
from schemas.shard import (
    COVER_ROWS,
    COVERAGE_GAINS,
    COVERS,
    GAIN_DTYPE,
    GAIN_TOTALS,
    GRID_FRAME,
    GRID_HITS,
    GRID_MISSES,
    GT_KEYS,
    MASK_DTYPE,
    OFFSET_DTYPE,
    VIEW_GAINS,
    ShardAttributes,
    keys_array,
    offsets_array,
    ordered_points,
    point_order,
)
from schemas.version import SCHEMA_VERSION
from storage import ShardPayload


def task_payload(result: TaskResult, config: GenerationConfig, schema_version: int = SCHEMA_VERSION) -> ShardPayload:
    """The shard and index rows of one task in layout ``schema_version`` (a dataset keeps its own
    version, so a task added to a version-1 dataset leaves the label ambiguity out)."""
    samples = result.samples
    arrays: dict[str, npt.NDArray[Any]] = {
        "masks": np.array([[s.case, s.label] for s in samples], dtype=MASK_DTYPE).reshape(-1, 2),
        GT_KEYS: keys_to_int16(unpack_keys(result.sets.ground_truth)),
    }
    clouds = [s.points for s in samples]
    if ordered_points(schema_version, "points"):
        clouds = [_in_point_order(s.points, config.seed, result, s.case) for s in samples]
    for name, sets in (
        ("points", clouds),
        ("observed", [s.observed for s in samples]),
        ("visible", list(result.sets.visible)),
        ("refined", list(result.sets.refined)),
    ):
        keys, offsets = _flatten(sets)
        arrays[keys_array(name)] = keys
        arrays[offsets_array(name)] = offsets
    meta = result.metadata
    attributes = ShardAttributes(
        schema_version=schema_version,
        task_id=result.task_id,
        object_id=result.object_id,
        object_name=result.object_name,
        rotation=result.rotation,
        attempt_id="",
        num_views=config.num_views,
        num_samples=len(samples),
        voxel_size=config.voxel_size,
        grid_offset=config.grid_offset,
        config_hash=str(meta["config_hash"]),
        metadata={
            **meta,
            "cases": len(result.cases),
            "dropped_empty": result.dropped_empty,
            "failed_cases": [{"case": f.case, "message": f.message} for f in result.failures],
            "seconds": result.seconds,
        },
    )
    rows: dict[str, list[Any]] = {
        "sample_id": [s.sample_id for s in samples],
        "task_id": [result.task_id] * len(samples),
        "object_id": [result.object_id] * len(samples),
        "object_name": [result.object_name] * len(samples),
        "rotation": [result.rotation] * len(samples),
        "view_state": [s.case for s in samples],
        "label": [s.label for s in samples],
        "case_size": [s.case.bit_count() for s in samples],
        "label_size": [s.label.bit_count() for s in samples],
        "num_points": [int(s.points.size) for s in samples],
        "num_observed": [int(s.observed.size) for s in samples],
        "full_size": [s.full_size for s in samples],
        "universe_size": [s.universe_size for s in samples],
        "empty_label": [s.empty_label for s in samples],
        "solver_status": [s.cover.status for s in samples],
        "solver_objective": [s.cover.objective for s in samples],
        "solver_proof": [s.cover.proof for s in samples],
        "solver_seconds": [s.cover.seconds for s in samples],
        "rows_before": [s.cover.rows_before for s in samples],
        "rows_after": [s.cover.rows_after for s in samples],
        "refiner": [str(meta["refiner"])] * len(samples),
        "weights_id": [str(meta["weights_id"])] * len(samples),
        "device": [str(meta["device"])] * len(samples),
        "seed": [int(str(meta["seed"]))] * len(samples),
        "config_hash": [str(meta["config_hash"])] * len(samples),
        "schema_version": [schema_version] * len(samples),
    }
    if schema_version >= 2:
        _add_ambiguity(result, arrays, rows)
    if schema_version >= 3:
        _add_next_view(result, config, arrays, rows)
    return ShardPayload(attributes=attributes, arrays=arrays, index_rows=rows)


def _add_ambiguity(result: TaskResult, arrays: dict[str, npt.NDArray[Any]], rows: dict[str, list[Any]]) -> None:
    """Version 2: the task's cover rows, each sample's minimum covers, their count and support."""
    found = [s.cover.ambiguity for s in result.samples]
    ambiguities = [a for a in found if a is not None]
    if len(ambiguities) != len(found):
        raise ValueError(f"task {result.task_id}: labels without their minimum covers cannot make a version-2 shard")
    arrays[COVER_ROWS] = np.asarray(result.cover_rows, dtype=MASK_DTYPE)
    offsets = np.zeros(len(ambiguities) + 1, dtype=OFFSET_DTYPE)
    offsets[1:] = np.cumsum([len(a.covers) for a in ambiguities])
    arrays[COVERS] = np.array([c for a in ambiguities for c in a.covers], dtype=MASK_DTYPE)
    arrays[offsets_array(COVERS)] = offsets
    rows["label_support"] = [a.support for a in ambiguities]
    rows["min_covers"] = [a.count for a in ambiguities]
    rows["min_covers_exact"] = [a.exact for a in ambiguities]


def _add_next_view(
    result: TaskResult, config: GenerationConfig, arrays: dict[str, npt.NDArray[Any]], rows: dict[str, list[Any]]
) -> None:
    """Version 3: every view's two gains with the task's denominators, the best next view, and each
    view's cells of the occupancy grid."""
    gains = [s.gains for s in result.samples]
    found = [g for g in gains if g is not None]
    if result.grids is None or len(found) != len(gains):
        raise ValueError(f"task {result.task_id}: samples without next-view labels cannot make a version-3 shard")
    views = config.num_views
    arrays[VIEW_GAINS] = np.array([g.visible for g in found], dtype=GAIN_DTYPE).reshape(-1, views)
    arrays[COVERAGE_GAINS] = np.array([g.coverage for g in found], dtype=GAIN_DTYPE).reshape(-1, views)
    full_size = result.samples[0].full_size if result.samples else 0
    arrays[GAIN_TOTALS] = np.array([result.visible_size, full_size], dtype=np.uint64)
    arrays[GRID_FRAME] = result.grids.frame.as_array()
    arrays[GRID_HITS] = result.grids.hits
    arrays[GRID_MISSES] = result.grids.misses
    rows["visible_size"] = [result.visible_size] * len(found)
    rows["best_view"] = [g.best_view for g in found]
    rows["best_view_ties"] = [g.best_view_ties for g in found]
    rows["best_gain"] = [int(g.visible[g.best_view]) if g.best_view >= 0 else 0 for g in found]


def _in_point_order(points: npt.NDArray[np.int64], seed: int, result: TaskResult, case: int) -> npt.NDArray[np.int64]:
    """A case's cloud (packed keys) in the order version 4 stores it: `schemas.shard.point_order` of its
    sorted keys, so any run of stored points is a uniform random subset of the cloud."""
    # The rule permutes the sorted set, whatever order the caller holds it in (a sample's set is sorted
    # already: the check costs a twentieth of the sort it saves).
    ordered = points if bool((points[1:] > points[:-1]).all()) else np.sort(points)
    return ordered[point_order(seed, result.object_id, result.rotation, case, ordered.size)]


def _flatten(sets: Sequence[npt.NDArray[np.int64]]) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.int64]]:
    """Packed key sets -> one (K, 3) int16 array and N + 1 offsets."""
    offsets = np.zeros(len(sets) + 1, dtype=OFFSET_DTYPE)
    offsets[1:] = np.cumsum([len(s) for s in sets])
    flat = np.concatenate(list(sets)) if sets else np.empty(0, dtype=np.int64)
    return keys_to_int16(unpack_keys(flat)).reshape(-1, 3), offsets
