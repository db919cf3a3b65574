"""The ``none`` refiner: R(O) is empty, so P(O) = keys(O) (what the sensor saw, nothing more)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from datagen.pipeline.refine.base import RefineRequest


class NoRefiner:
    name = "none"
    weights_id = ""

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        return [np.empty(0, dtype=np.int64) for _ in requests]
