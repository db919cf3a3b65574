"""First-hit ray casting with Embree (embreex), refined to float64.

Embree intersects in float32. The triangle it reports is then intersected again in float64 (ray
against the triangle's plane), so a hit point is exact to float64 rounding given the triangle, and
keys computed from it do not depend on Embree's float32 rounding. Single-threaded by design: the
engine parallelises over tasks, not inside one.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

GRAZING_COSINE = 1e-12


class RayCaster:
    """An Embree scene of one triangle mesh, queried for first hits."""

    def __init__(self, vertices: npt.ArrayLike, faces: npt.ArrayLike) -> None:
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._scene,
            vertices=self.vertices.astype(np.float32),
            indices=self.faces.astype(np.int32),
        )
        corner = self.vertices[self.faces[:, 0]]
        normals = np.cross(self.vertices[self.faces[:, 1]] - corner, self.vertices[self.faces[:, 2]] - corner)
        lengths = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(lengths == 0, 1.0, lengths)
        # One row per triangle: unit normal and plane offset, gathered once per hit.
        self._planes = np.ascontiguousarray(np.hstack([normals, np.einsum("ij,ij->i", normals, corner)[:, None]]))
        self._origins32 = np.empty((0, 3), dtype=np.float32)

    def first_hits(
        self, origin: npt.ArrayLike, directions: npt.NDArray[np.float64], max_range: float
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
        """Distance along each unit direction to the first hit (inf for none within range) and the
        hit triangle (-1 for none), for rays from one ``origin``."""
        count = directions.shape[0]
        distance = np.full(count, np.inf)
        primitive = np.full(count, -1, dtype=np.int64)
        rows, hit_distance, hit_primitive, _ = self.cast(origin, directions, max_range)
        distance[rows] = hit_distance
        primitive[rows] = hit_primitive
        return distance, primitive

    def cast(
        self,
        origin: npt.ArrayLike,
        directions: npt.NDArray[np.float64],
        max_range: float,
        directions32: npt.NDArray[np.float32] | None = None,
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """The rays that hit within ``max_range``: their rows, float64 distances, triangles and
        directions (gathered once here, so callers need not gather them again).

        Embree is asked only for the hit triangle (its cheapest query, as fast as Open3D's cast);
        the distance comes from intersecting that triangle's plane in float64, so hit points do
        not depend on Embree's float32 rounding. ``directions32`` may pass the float32 copy of the
        directions when the caller already has it.
        """
        count = directions.shape[0]
        if count == 0:
            return np.empty(0, dtype=np.int64), np.empty(0), np.empty(0, dtype=np.int64), np.empty((0, 3))
        start = np.asarray(origin, dtype=np.float64)
        if self._origins32.shape[0] < count:
            self._origins32 = np.empty((count, 3), dtype=np.float32)
        origins32 = self._origins32[:count]
        origins32[:] = start.astype(np.float32)
        if directions32 is None:
            directions32 = directions.astype(np.float32)
        primitive = self._scene.run(origins32, directions32, output=0)
        rows = np.flatnonzero(primitive >= 0)
        prim = primitive[rows].astype(np.int64)
        planes = self._planes[prim]
        hit_directions = directions[rows]
        cosine = np.einsum("ij,ij->i", planes[:, :3], hit_directions)
        numerator = planes[:, 3] - planes[:, :3] @ start
        grazing = np.abs(cosine) <= GRAZING_COSINE
        cosine[grazing] = 1.0
        distance = numerator / cosine
        if grazing.any():
            # A ray in the triangle's plane has no plane intersection: keep Embree's own distance.
            chosen = rows[grazing]
            distance[grazing] = self._scene.run(
                np.ascontiguousarray(origins32[chosen]), np.ascontiguousarray(directions32[chosen]), query="DISTANCE"
            )
        if distance.size and distance.max() > max_range:
            keep = distance <= max_range
            return rows[keep], distance[keep], prim[keep], hit_directions[keep]
        return rows, distance, prim, hit_directions
