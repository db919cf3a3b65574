"""Ground truth P_gt (docs/pipeline.md section 1.7): keys of a dense, seeded surface sampling.

Each key keeps one representative surface point, the sample with the lowest index, so the choice
never depends on sort stability or thread count. Imaging may add keys it hits that the sampling
missed (`with_hits`); those take the first hit point as their representative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.keys import KeyGrid, pack_keys

DENSE_GRID_LIMIT = 64_000_000


@dataclass(frozen=True)
class GroundTruth:
    """P_gt as sorted unique packed keys and one surface point per key."""

    keys: npt.NDArray[np.int64]
    points: npt.NDArray[np.float64]
    sampled: int
    """How many of the keys come from the surface sampling (the rest were added by imaging)."""

    def __len__(self) -> int:
        return int(self.keys.size)

    def with_hits(self, hit_keys: npt.NDArray[np.int64], hit_points: npt.NDArray[np.floating]) -> GroundTruth:
        """P_gt united with imaged keys; new keys take their first hit (in the given order) as point."""
        unique, first = np.unique(hit_keys, return_index=True)
        new = ~np.isin(unique, self.keys, assume_unique=True)
        if not new.any():
            return self
        keys = np.concatenate([self.keys, unique[new]])
        points = np.concatenate([self.points, np.asarray(hit_points, dtype=np.float64)[first[new]]])
        order = np.argsort(keys, kind="stable")
        return GroundTruth(keys=keys[order], points=points[order], sampled=self.sampled)


def sample_ground_truth(
    vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    voxel_size: float,
    grid_offset: tuple[float, float, float],
    density: float,
    rng: np.random.Generator,
) -> GroundTruth:
    """Area-weighted sampling with ``density`` samples per voxel_size^2 of area, keyed.

    Samples are numbered face by face (face counts drawn multinomially by area), and each key keeps
    its lowest-numbered sample.
    """
    triangles = vertices[faces]
    edge_a = triangles[:, 1] - triangles[:, 0]
    edge_b = triangles[:, 2] - triangles[:, 0]
    areas = 0.5 * np.linalg.norm(np.cross(edge_a, edge_b), axis=1)
    total = float(areas.sum())
    count = max(1, math.ceil(total / voxel_size**2 * density))
    per_face = rng.multinomial(count, areas / total)
    uniforms = rng.random((2, count))
    flip = uniforms.sum(axis=0) > 1.0
    uniforms[:, flip] = 1.0 - uniforms[:, flip]
    r1, r2 = uniforms
    # Column by column with np.repeat: ~4x faster than gathering (count, 3) rows by face index.
    grid = KeyGrid.around(vertices, voxel_size, grid_offset)
    linear = np.zeros(count, dtype=np.int64)
    for axis in range(3):
        coordinate = _sample_coordinate(triangles[:, 0, axis], edge_a[:, axis], edge_b[:, axis], per_face, r1, r2)
        coordinate /= voxel_size
        coordinate += grid_offset[axis]
        linear *= grid.dims[axis]
        linear += np.floor(coordinate).astype(np.int64) - grid.low[axis]
    if grid.size <= DENSE_GRID_LIMIT:
        first = grid.first_occurrences(linear)
    else:
        _, first = np.unique(linear, return_index=True)
    cell_keys = grid.keys_of(linear[first])
    face = np.searchsorted(np.cumsum(per_face), first, side="right")
    points = np.stack(
        [
            _sample_coordinate(
                triangles[face, 0, axis], edge_a[face, axis], edge_b[face, axis], 1, r1[first], r2[first]
            )
            for axis in range(3)
        ],
        axis=1,
    )
    return GroundTruth(keys=pack_keys(cell_keys), points=points, sampled=int(first.size))


def _sample_coordinate(
    corner: npt.NDArray[np.float64],
    edge_a: npt.NDArray[np.float64],
    edge_b: npt.NDArray[np.float64],
    repeats: npt.NDArray[np.int64] | int,
    r1: npt.NDArray[np.float64],
    r2: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """One coordinate of corner + r1 * a + r2 * b, evaluated in one fixed order so that recomputing a
    chosen sample gives bit-identical values (its key must not change)."""
    value = np.repeat(corner, repeats)
    value += r1 * np.repeat(edge_a, repeats)
    value += r2 * np.repeat(edge_b, repeats)
    return value
