"""Voxel keys: the integer identity of every point in the pipeline (docs/pipeline.md section 0).

A key is ``floor(p / voxel_size + grid_offset)`` per axis, computed in float64. The offset moves the
grid off the flat faces that centring and round sizes put exactly on voxel boundaries. Sets of keys
are handled as sorted unique int64 "packed" scalars (21 bits per axis), which makes unions,
intersections and membership sorts, ``np.isin`` and ``np.searchsorted`` calls (`sorted_unique`,
`union_keys`: numpy's own ``np.unique`` is far slower on large integer arrays).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

KEY_BITS = 21
KEY_BIAS = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
INT16_RANGE = (-(1 << 15), (1 << 15) - 1)

FloatArray = npt.NDArray[np.floating]
KeyArray = npt.NDArray[np.int64]


def sorted_unique(values: npt.ArrayLike) -> npt.NDArray[np.integer]:
    """The distinct values of an integer array, ascending: exactly ``np.unique(values)``, faster.

    numpy >= 2.3 answers a plain ``np.unique`` of integers from a hash table, then sorts: ~1 s for
    1.2 M int64 keys on the 2-core machine, where a sort and a neighbour comparison take 65 ms. The
    stable sort (timsort for int64) also merges already sorted runs in linear time, which is what a
    union of sorted key sets is: 4 sets of 300 k keys unite in 13 ms instead of 830.
    """
    flat = np.sort(np.asarray(values).reshape(-1), kind="stable")
    if flat.size < 2:
        return flat
    keep = np.empty(flat.size, dtype=bool)
    keep[0] = True
    np.not_equal(flat[1:], flat[:-1], out=keep[1:])
    return flat[keep]


def union_keys(*key_sets: npt.NDArray[np.int64]) -> KeyArray:
    """The sorted union of sorted packed key sets (``np.union1d`` of them, by `sorted_unique`)."""
    if not key_sets:
        return np.empty(0, dtype=np.int64)
    return np.asarray(sorted_unique(np.concatenate(key_sets)), dtype=np.int64)


def points_to_keys(points: npt.ArrayLike, voxel_size: float, grid_offset: npt.ArrayLike) -> KeyArray:
    """Integer keys (N, 3) of points (N, 3), computed in float64."""
    scaled = np.asarray(points, dtype=np.float64) / voxel_size + np.asarray(grid_offset, dtype=np.float64)
    return np.floor(scaled).astype(np.int64)


def key_centres(keys: npt.ArrayLike, voxel_size: float, grid_offset: npt.ArrayLike) -> FloatArray:
    """The point of each key: its centre ``(key + 0.5 - offset) * voxel_size``, float64."""
    offset = np.asarray(grid_offset, dtype=np.float64)
    return (np.asarray(keys, dtype=np.float64) + 0.5 - offset) * voxel_size


def pack_keys(keys: npt.ArrayLike) -> KeyArray:
    """Pack (N, 3) keys into int64 scalars whose order is the lexicographic (x, y, z) order."""
    k = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    biased = k + KEY_BIAS
    if biased.size and (biased.min() < 0 or biased.max() > KEY_MASK):
        raise ValueError(f"key out of the packable range +-{KEY_BIAS}")
    return (biased[:, 0] << (2 * KEY_BITS)) | (biased[:, 1] << KEY_BITS) | biased[:, 2]


def unpack_keys(packed: npt.ArrayLike) -> KeyArray:
    """Inverse of `pack_keys`: (N,) int64 -> (N, 3) int64."""
    p = np.asarray(packed, dtype=np.int64).reshape(-1)
    out = np.empty((p.size, 3), dtype=np.int64)
    out[:, 0] = (p >> (2 * KEY_BITS)) & KEY_MASK
    out[:, 1] = (p >> KEY_BITS) & KEY_MASK
    out[:, 2] = p & KEY_MASK
    return out - KEY_BIAS


def points_to_packed(points: npt.ArrayLike, voxel_size: float, grid_offset: npt.ArrayLike) -> KeyArray:
    return pack_keys(points_to_keys(points, voxel_size, grid_offset))


def keys_to_int16(keys: npt.ArrayLike) -> npt.NDArray[np.int16]:
    """Keys as int16 triples for writing, refusing any key that would wrap."""
    k = np.asarray(keys, dtype=np.int64)
    if k.size and (k.min() < INT16_RANGE[0] or k.max() > INT16_RANGE[1]):
        raise ValueError(f"key outside int16 range {INT16_RANGE}: cannot be written losslessly")
    return k.astype(np.int16)


class KeyGrid:
    """A dense box of keys, numbered so that numeric order is the lexicographic (x, y, z) order.

    Within one task every key lies in the box of the mesh's keys, so sets of keys become boolean
    arrays over the box: deduplication, membership and "first occurrence" are linear-time array
    operations instead of sorts of millions of values.
    """

    def __init__(self, low: npt.ArrayLike, high: npt.ArrayLike) -> None:
        self.low = np.asarray(low, dtype=np.int64)
        self.dims = np.asarray(high, dtype=np.int64) - self.low + 1
        self.size = int(np.prod(self.dims))

    @classmethod
    def around(cls, points: npt.ArrayLike, voxel_size: float, grid_offset: npt.ArrayLike, margin: int = 1) -> KeyGrid:
        """The box of the keys of ``points`` (e.g. a mesh's vertices), grown by ``margin`` keys."""
        p = np.asarray(points, dtype=np.float64)
        low = points_to_keys(p.min(axis=0, keepdims=True), voxel_size, grid_offset)[0] - margin
        high = points_to_keys(p.max(axis=0, keepdims=True), voxel_size, grid_offset)[0] + margin
        return cls(low, high)

    def linear_of_points(
        self, points: npt.NDArray[np.float64], voxel_size: float, grid_offset: npt.ArrayLike, clip: bool = False
    ) -> KeyArray:
        """Cell numbers of the keys of points, column by column (no (N, 3) temporaries).

        ``clip`` maps keys outside the box to its border cells (for callers that only compare)."""
        offset = np.asarray(grid_offset, dtype=np.float64)
        linear = np.zeros(points.shape[0], dtype=np.int64)
        for axis in range(3):
            column = points[:, axis] / voxel_size
            column += offset[axis]
            index = np.floor(column).astype(np.int64) - self.low[axis]
            if clip:
                np.clip(index, 0, self.dims[axis] - 1, out=index)
            linear *= self.dims[axis]
            linear += index
        return linear

    def linear_of_keys(self, keys: npt.ArrayLike) -> KeyArray:
        shifted = np.asarray(keys, dtype=np.int64).reshape(-1, 3) - self.low
        return (shifted[:, 0] * self.dims[1] + shifted[:, 1]) * self.dims[2] + shifted[:, 2]

    def keys_of(self, linear: npt.ArrayLike) -> KeyArray:
        return np.stack(np.unravel_index(np.asarray(linear, dtype=np.int64), tuple(self.dims)), axis=1) + self.low

    def packed_of(self, linear: npt.ArrayLike) -> KeyArray:
        return pack_keys(self.keys_of(linear))

    def unique(self, linear: npt.NDArray[np.int64]) -> KeyArray:
        """Sorted distinct cell numbers."""
        present = np.zeros(self.size, dtype=bool)
        present[linear] = True
        return np.flatnonzero(present)

    def first_occurrences(self, linear: npt.NDArray[np.int64]) -> KeyArray:
        """Index of the first element of every distinct cell, in increasing cell (= key) order."""
        count = linear.shape[0]
        lowest = np.full(self.size, count, dtype=np.int64)
        np.minimum.at(lowest, linear, np.arange(count, dtype=np.int64))
        return lowest[lowest < count]
