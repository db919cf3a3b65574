"""What a reader keeps of each sample between reading a shard and making a batch: `Held` values.

A `storage.samples.SampleField` reads its values for some rows of a shard as one `Held`; every
reader then does the same three things with them, whatever the field: take some samples (`take`),
put pieces read from several shards in position order (`placed`: a whole in-memory load, or one
batch of a stream drawn from several shards), and hand the batch's values to the field's `finish`.
Two shapes cover the fields: `Stacked` (one fixed-shape row a sample) and `Ragged` (a run of rows a
sample: a cloud's keys, a listing of covers). A field may bring its own (the occupancy grid's
`storage.samples.CaseGrids` keeps a task's ray cells once, not a grid a sample).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, Self, TypeVar

import numpy as np
import numpy.typing as npt

Positions = npt.NDArray[np.int64]
HeldT = TypeVar("HeldT", bound="Held")


class Held(Protocol):
    """Some samples' values of one field, in sample order."""

    def __len__(self) -> int: ...

    def take(self, positions: Positions) -> Self:
        """The samples at ``positions`` (any order, repeats allowed), in that order."""
        ...

    @classmethod
    def placed(cls, pieces: Sequence[tuple[Positions, Self]], total: int) -> Self:
        """One `Held` of ``total`` samples from pieces (positions, their values): every position from 0
        to total - 1 is in exactly one piece."""
        ...


def placed(pieces: Sequence[tuple[Positions, HeldT]], total: int) -> HeldT:
    """`Held.placed` of the pieces' own type (``pieces`` is not empty)."""
    return type(pieces[0][1]).placed(pieces, total)


@dataclass(frozen=True)
class Stacked:
    """One fixed-shape row per sample: ``values`` is (S, ...)."""

    values: npt.NDArray[Any]

    def __len__(self) -> int:
        return int(self.values.shape[0])

    def take(self, positions: Positions) -> Stacked:
        return Stacked(self.values[positions])

    @classmethod
    def placed(cls, pieces: Sequence[tuple[Positions, Stacked]], total: int) -> Stacked:
        if _in_order(pieces, total):
            return Stacked(np.concatenate([held.values for _, held in pieces]))
        first = pieces[0][1].values
        out = np.zeros((total, *first.shape[1:]), dtype=first.dtype)
        for positions, held in pieces:
            out[positions] = held.values
        return Stacked(out)


@dataclass(frozen=True)
class Ragged:
    """A run of rows per sample: sample ``p``'s are ``values[offsets[p]:offsets[p + 1]]``."""

    values: npt.NDArray[Any]
    offsets: npt.NDArray[np.int64]
    """(S + 1,) int64, from 0."""

    def __len__(self) -> int:
        return int(self.offsets.size - 1)

    @classmethod
    def of_rows(cls, values: npt.NDArray[Any], offsets: npt.ArrayLike, rows: Positions) -> Ragged:
        """The runs of ``rows`` of a stored ragged array (``values`` with its ``offsets``)."""
        bounds = np.asarray(offsets, dtype=np.int64)
        starts = bounds[rows]
        sizes = bounds[rows + 1] - starts
        if rows.size and np.array_equal(rows, np.arange(rows[0], rows[0] + rows.size)):
            taken = values[starts[0] : starts[0] + int(sizes.sum())]  # a run of rows: one slice
        else:
            taken = values[ragged_index(starts, sizes)]
        return cls(taken, sizes_to_offsets(sizes))

    def sizes(self) -> npt.NDArray[np.int64]:
        return np.diff(self.offsets)

    def of(self, position: int) -> npt.NDArray[Any]:
        """Sample ``position``'s rows."""
        return self.values[self.offsets[position] : self.offsets[position + 1]]

    def take(self, positions: Positions) -> Ragged:
        return Ragged.of_rows(self.values, self.offsets, np.asarray(positions, dtype=np.int64))

    @classmethod
    def placed(cls, pieces: Sequence[tuple[Positions, Ragged]], total: int) -> Ragged:
        sizes = np.zeros(total, dtype=np.int64)
        for positions, held in pieces:
            sizes[positions] = held.sizes()
        offsets = sizes_to_offsets(sizes)
        first = pieces[0][1].values
        if _in_order(pieces, total):
            return Ragged(np.concatenate([held.values for _, held in pieces]).astype(first.dtype, copy=False), offsets)
        values = np.empty((int(offsets[-1]), *first.shape[1:]), dtype=first.dtype)
        for positions, held in pieces:
            values[ragged_index(offsets[positions], held.sizes())] = held.values
        return Ragged(values, offsets)


def _in_order(pieces: Sequence[tuple[Positions, Any]], total: int) -> bool:
    """Whether the pieces hold positions 0..total-1 one after another (a whole load read in order)."""
    read = np.concatenate([positions for positions, _ in pieces]) if pieces else np.zeros(0, np.int64)
    return read.size == total and bool(np.array_equal(read, np.arange(total)))


def ragged_index(starts: npt.NDArray[np.int64], sizes: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Flat indices of the slices ``starts[i]:starts[i] + sizes[i]``, one after another."""
    total = int(sizes.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    begins = np.zeros(sizes.size, dtype=np.int64)
    np.cumsum(sizes[:-1], out=begins[1:])
    return np.repeat(starts - begins, sizes) + np.arange(total, dtype=np.int64)


def sizes_to_offsets(sizes: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    offsets = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    return offsets
