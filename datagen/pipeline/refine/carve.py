"""The ``carve`` refiner: space carving, no learning.

R(O) = every band key that no view of O saw empty. It over-predicts (everything hidden behind the
surface counts as occupied); the pipeline's intersection with P_gt forgives that in the labels but
not in the network's input cloud. It is the baseline a learned refiner must beat.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from datagen.pipeline.refine.base import RefineRequest, band_keys
from datagen.pipeline.refine.freespace import DepthBuffers, sensor_empty
from schemas.config import GenerationConfig


class CarveRefiner:
    name = "carve"
    weights_id = ""

    def __init__(self, config: GenerationConfig) -> None:
        self.config = config
        self.depth_buffers = DepthBuffers()  # a task's cases reuse its views' buffers (same result)

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        config = self.config
        results = []
        for request in requests:
            observation = request.observation
            band = band_keys(observation.keys, config.band_keys_sq)
            unknown = np.setdiff1d(band, observation.keys, assume_unique=True)
            empty = sensor_empty(
                unknown, observation, config.camera, config.voxel_size, config.grid_offset, self.depth_buffers
            )
            results.append(unknown[~empty])
        return results
