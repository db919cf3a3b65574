"""`datagen shards validate --all` for the next-view labels (schema version 3): the occupancy grid's
ray cells walked again from the stored V_i and P_gt, and the index's best next view against the
stored gains. `storage.validate` recounts the gains themselves with numpy alone."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from datagen.pipeline.keys import pack_keys
from datagen.pipeline.occupancy import view_grids
from schemas.config import GenerationConfig
from schemas.shard import (
    GAIN_TOTALS,
    GRID_FRAME,
    GRID_HITS,
    GRID_MISSES,
    GT_KEYS,
    MASKS,
    VIEW_GAINS,
    VIEW_STATE_COLUMN,
    keys_array,
    offsets_array,
)
from storage.samples import best_views
from storage.shards import ShardReader

GRID = "grid"
BEST_VIEW = "best-view"


def next_view_problems(
    shard: ShardReader,
    config: GenerationConfig,
    positions: npt.NDArray[np.float64],
    indexed: Sequence[tuple[int, int, int, int] | None],
) -> list[tuple[int | None, str, str]]:
    """(row or None for the shard, kind, text) of every disagreement: the stored grid arrays against a
    fresh ray walk, and each row's (visible size, best view, ties, best gain) in the index (``indexed``, None
    where the index has no row) against the stored gains."""
    num_views = shard.attributes.num_views
    keys, offsets = shard.array(keys_array("visible")), shard.array(offsets_array("visible"))
    visible = [pack_keys(keys[offsets[v] : offsets[v + 1]]) for v in range(num_views)]
    walked = view_grids(visible, pack_keys(shard.array(GT_KEYS)), positions, config.voxel_size, config.grid_offset)
    found: list[tuple[int | None, str, str]] = []
    for name, fresh in ((GRID_FRAME, walked.frame.as_array()), (GRID_HITS, walked.hits), (GRID_MISSES, walked.misses)):
        if not np.array_equal(shard.array(name), fresh):
            found.append((None, GRID, f"{name} differs from the ray walk over the stored V_i and P_gt"))
    gains = shard.array(VIEW_GAINS)
    cases = shard.array(MASKS)[:, VIEW_STATE_COLUMN]
    best, ties = best_views(gains, cases, num_views)
    visible_size = int(shard.array(GAIN_TOTALS)[0])
    for row, stated in enumerate(indexed):
        if stated is None:
            continue
        gain = int(gains[row, best[row]]) if best[row] >= 0 else 0
        expected = (visible_size, int(best[row]), int(ties[row]), gain)
        if tuple(stated) != expected:
            what = "(visible size, best view, ties, best gain)"
            text = f"the index says {what} {tuple(stated)}, the stored gains give {expected}"
            found.append((row, BEST_VIEW, text))
    return found
