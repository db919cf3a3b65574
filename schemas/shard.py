"""The shard layout: one Zarr v3 group per task attempt, holding every sample of the task (from
version 5 in one file: an uncompressed ZIP of the group's members, `SINGLE_FILE_SINCE`).

Every point is a voxel centre, so points are stored as their integer keys (int16 triples) and read
back as float32 centres ``(key + 0.5 - grid_offset) * voxel_size``. Variable-length per-sample sets
are flat key arrays plus offsets (sample i owns rows ``offsets[i]:offsets[i+1]``). Arrays are few
and written once each, because zarr rewrites a whole shard on every partial write and costs about a
millisecond per array access.

Arrays of a shard group (N samples, n views):

=====================  ============  ===========  ==============================================
name                   dtype         shape        meaning
=====================  ============  ===========  ==============================================
``masks``              uint64        (N, 2)       column 0: view_state (case S), 1: label (L)
``points_keys``        int16         (P, 3)       keys of P(O_S) of every sample, concatenated
                                                  (version 4: each cloud in `point_order`)
``points_offsets``     int64         (N + 1,)     sample i owns ``points_keys[o[i]:o[i+1]]``
``observed_keys``      int16         (Q, 3)       keys of O_S (what the input views saw)
``observed_offsets``   int64         (N + 1,)
``visible_keys``       int16         (V, 3)       per-task V_i, views concatenated
``visible_offsets``    int64         (n + 1,)
``refined_keys``       int16         (R, 3)       per-task P_i = P(O_i) intersected with P_gt
``refined_offsets``    int64         (n + 1,)
``gt_keys``            int16         (G, 3)       per-task P_gt
``cover_rows``         uint64        (M,)         per-task undominated masks of P_full (version 2)
``covers``             uint64        (C,)         each sample's minimum covers (version 2)
``covers_offsets``     int64         (N + 1,)     sample i owns ``covers[o[i]:o[i+1]]``
``view_gains``         uint32        (N, n)       keys of V_i no view of S sees (version 3)
``coverage_gains``     uint32        (N, n)       keys of C_i no C_s of S holds (version 3)
``gain_totals``        uint64        (2,)         per-task denominators: |union of V_i|, |P_full|
``grid_frame``         float64       (4,)         per-task grid: corner x, y, z and cell size, m
``grid_hits``          uint8         (n, 4096)    per view, bit-packed cells its rays end in
``grid_misses``        uint8         (n, 4096)    per view, bit-packed cells they only cross
=====================  ============  ===========  ==============================================

Version 2 lets a reader judge any view set without a solver: U(S)'s set cover rows are exactly the
``cover_rows`` that miss S (a view set covers U when it meets each of them), and ``covers`` lists
the minimum covers the label was chosen from (all of them, or the label and the first others up to
the config's ``label_cover_cap``; the index says how many there are and whether that is exact).

Version 3 adds the next-best-view families' labels (docs/pipeline.md section 8.1-8.2): every view's
gain counted over the visibility and over the coverage sets, with both denominators, and the
planners' 32^3 occupancy grid, kept as each view's ray cells once per task; a case's grid is its
views inserted in ascending order (`storage.samples.case_grid`).

Version 4 stores each sample's refined cloud (``points_keys``) in a seeded random order
(`point_order`: a permutation of the sorted set from the stream of the dataset's seed, the task and
the case), in inner chunks of a few thousand rows, so that any run of consecutive stored points is a
uniform random subset of the cloud and a reader wanting N of them decodes one or two chunks instead
of the whole cloud (`storage.samples.cloud_positions`).

Every other key set of a sample or view, and a version-4 cloud once put back in `point_order`, is
sorted lexicographically (x, y, z) and unique. Rows are ordered by (case size, case mask). Group
attributes (`ShardAttributes`) say what the task was.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict

from schemas.version import SCHEMA_VERSION

MASKS = "masks"
VIEW_STATE_COLUMN = 0
LABEL_COLUMN = 1

KEY_SETS = ("points", "observed")
"""Per-sample key sets: ``<name>_keys`` plus ``<name>_offsets`` with N + 1 entries."""
TASK_SETS = ("visible", "refined")
"""Per-view key sets of the task: ``<name>_keys`` plus ``<name>_offsets`` with n + 1 entries."""
GT_KEYS = "gt_keys"
COVER_ROWS = "cover_rows"
"""Version 2: the task's undominated P_full masks, sorted (the rows of every case's set cover)."""
COVERS = "covers"
"""Version 2: each sample's minimum covers (masks), sorted as tuples of views, with offsets."""
VIEW_GAINS = "view_gains"
COVERAGE_GAINS = "coverage_gains"
GAIN_TOTALS = "gain_totals"
GRID_FRAME = "grid_frame"
GRID_HITS = "grid_hits"
GRID_MISSES = "grid_misses"
NEXT_VIEW_ARRAYS = (VIEW_GAINS, COVERAGE_GAINS, GAIN_TOTALS, GRID_FRAME, GRID_HITS, GRID_MISSES)
"""Version 3: the next-best-view labels and the occupancy grid's per-view ray cells."""
GAIN_DTYPE = np.dtype(np.uint32)
ORDERED_POINTS_SINCE = 4
SINGLE_FILE_SINCE = 5
"""The first layout version keeping a task's group in one ZIP file (``<attempt>.zarr.zip``) instead of a
folder of about 40 files (``<attempt>.zarr``); the arrays and their encoding are version 4's."""
"""The first layout version whose ``points_keys`` hold each cloud in `point_order`."""
POINT_ORDER_PURPOSE = 4
"""The purpose number of the point-order stream among a task's random streams (docs/pipeline.md
section 9; `datagen.pipeline.random_streams.Purpose.POINT_ORDER`)."""

KEY_DTYPE = np.dtype(np.int16)
OFFSET_DTYPE = np.dtype(np.int64)
MASK_DTYPE = np.dtype(np.uint64)


def keys_array(name: str) -> str:
    return f"{name}_keys"


def offsets_array(name: str) -> str:
    return f"{name}_offsets"


def point_order(seed: int, object_id: str, rotation: int, case: int, count: int) -> npt.NDArray[np.int64]:
    """Where each stored point of a version-4 cloud comes from: stored row ``j`` holds key
    ``order[j]`` of the case's sorted cloud of ``count`` keys. A permutation from stream
    ``(seed, object id prefix, rotation, POINT_ORDER_PURPOSE, case mask)``, so a fresh generation, a
    relabel and a validation all find the same order from the sample's identity alone."""
    entropy = [seed, int(object_id[:16], 16), rotation, POINT_ORDER_PURPOSE, case]
    return np.random.default_rng(np.random.SeedSequence(entropy)).permutation(count).astype(np.int64)


def ordered_points(schema_version: int, name: str) -> bool:
    """True for the key set ``name`` (``points``, ``observed``) of a layout storing it in `point_order`."""
    return name == "points" and schema_version >= ORDERED_POINTS_SINCE


def single_file(schema_version: int) -> bool:
    """True for a layout keeping each task's group in one ZIP file."""
    return schema_version >= SINGLE_FILE_SINCE


def shard_suffix(schema_version: int) -> str:
    """How a task attempt's shard path ends in layout ``schema_version``."""
    return ".zarr.zip" if single_file(schema_version) else ".zarr"


def array_names(schema_version: int = SCHEMA_VERSION) -> list[str]:
    """Every array a shard group of this layout version holds, sorted."""
    names = [MASKS, GT_KEYS]
    for name in (*KEY_SETS, *TASK_SETS):
        names += [keys_array(name), offsets_array(name)]
    if schema_version >= 2:
        names += [COVER_ROWS, COVERS, offsets_array(COVERS)]
    if schema_version >= 3:
        names += list(NEXT_VIEW_ARRAYS)
    return sorted(names)


class ShardAttributes(BaseModel):
    """Attributes of a shard group: the task, its attempt and how to turn keys into points."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    schema_version: int
    task_id: str
    object_id: str
    object_name: str
    rotation: int
    attempt_id: str
    num_views: int
    num_samples: int
    voxel_size: float
    grid_offset: tuple[float, float, float]
    config_hash: str
    metadata: dict[str, Any]
    """Per-task metadata shared by every sample (refiner, weights id, device, seed, timings...)."""
