"""The refiner interface and the band every refiner works in.

A refiner receives a batch of observations (all single views of a task, then all multi-view
cases), so that a learned model can batch its work, and returns R(O) for each: packed keys within
the band (|dk|^2 <= band_keys_sq around a key of O) that it predicts occupied. P(O) = keys(O)
united with R(O). R(O) may depend on O, the refiner, its config, its weights and a seed, nothing
else; `RefineRequest` carries the seed material.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import KeyGrid, unpack_keys


@dataclass(frozen=True)
class RefineRequest:
    """One observation to refine, with what seeds its randomness (PIPELINE.md section 9)."""

    observation: Observation
    seed: int
    object_id: str
    rotation: int

    @property
    def mask(self) -> int:
        return self.observation.mask


class Refiner(Protocol):
    """Maps observations to their predicted occupied band keys."""

    name: str
    weights_id: str
    """sha256 of the weights file ('' for refiners without weights)."""

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        """R(O) for each request, as sorted packed keys inside the band of O."""
        ...


def refined_keys(observation: Observation, refinement: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """P(O) = keys(O) united with R(O), sorted packed keys."""
    return np.union1d(observation.keys, refinement)


def band_offsets(radius_sq: int) -> npt.NDArray[np.int64]:
    """Integer offsets dk with |dk|^2 <= radius_sq, sorted."""
    r = int(np.floor(np.sqrt(radius_sq)))
    axis = np.arange(-r, r + 1)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid[(grid * grid).sum(axis=1) <= radius_sq]


def band_keys(keys: npt.NDArray[np.int64], radius_sq: int) -> npt.NDArray[np.int64]:
    """Every key within the band of a set of packed keys (the keys themselves included), sorted.

    A binary dilation of the keys' box by the ball of offsets: linear in the box, where adding all
    515 offsets to every key and sorting would be ~50x slower.
    """
    if keys.size == 0:
        return keys
    offsets = band_offsets(radius_sq)
    reach = int(np.abs(offsets).max())
    centres = unpack_keys(keys)
    grid = KeyGrid(centres.min(axis=0) - reach, centres.max(axis=0) + reach)
    occupied = np.zeros(grid.size, dtype=bool)
    occupied[grid.linear_of_keys(centres)] = True
    ball = np.zeros((2 * reach + 1,) * 3, dtype=bool)
    ball[tuple((offsets + reach).T)] = True
    dilated = ndimage.binary_dilation(occupied.reshape(tuple(grid.dims)), structure=ball)
    return grid.packed_of(np.flatnonzero(dilated))
