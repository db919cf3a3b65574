"""Random streams (docs/pipeline.md section 9): one root seed, one independent stream per use.

``SeedSequence([seed, object_id_prefix, rotation, PURPOSE(, mask)])``: the draws of one use never
depend on how many other uses ran before it, on which worker, or in which order.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from schemas.shard import POINT_ORDER_PURPOSE


class Purpose(IntEnum):
    GROUND_TRUTH = 0
    CASES = 1
    REFINER_NOISE = 2
    EVALUATION = 3
    """`datagen evaluate`'s seeded baselines (the random planner), per initial view."""
    POINT_ORDER = POINT_ORDER_PURPOSE
    """Per case: the order a version-4 shard stores the refined cloud in (`schemas.shard.point_order`,
    which draws it; storage and validation need it without the pipeline)."""


def stream(seed: int, object_id: str, rotation: int, purpose: Purpose, mask: int | None = None) -> np.random.Generator:
    """The generator for one use within one task (and one case, for refiner noise)."""
    entropy = [seed, int(object_id[:16], 16), rotation, int(purpose)]
    if mask is not None:
        entropy.append(mask)
    return np.random.default_rng(np.random.SeedSequence(entropy))
