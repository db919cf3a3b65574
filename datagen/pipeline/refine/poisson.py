"""The ``poisson`` refiner: screened Poisson surface reconstruction (Open3D), the classical baseline.

For each observation: normals from the k nearest observed points, each flipped to face the camera
that saw its point (a depth sensor only sees surfaces facing it, so this orientation is exact where
a global propagation could flip whole patches); screened Poisson reconstruction of that oriented
cloud; R(O) = the unknown band keys (band minus keys(O) minus keys the sensor saw empty) whose
centre lies inside the reconstructed surface. Poisson closes whatever the views did not see with a
smooth membrane, so it fills hidden surface well on blobby shapes and bulges on thin or open ones.

Open3D runs single-threaded here (one worker per core already), which also makes the octree
solve deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import open3d as o3d

from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.refine.base import RefineRequest, band_keys
from datagen.pipeline.refine.freespace import sensor_empty
from schemas.config import GenerationConfig

NORMAL_NEIGHBOURS = 24
"""Points per normal estimate: enough to average out one-voxel key quantisation."""
MIN_POINTS = NORMAL_NEIGHBOURS
"""Below this many observed points there is no surface to fit; R(O) is empty."""
BOX_SCALE = 1.2
"""Octree cube edge over the cloud's bounding-box diagonal extent: room for the closing membrane."""


class PoissonRefiner:
    name = "poisson"
    weights_id = ""

    def __init__(self, config: GenerationConfig) -> None:
        self.config = config
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        return [self._refine_one(request) for request in requests]

    def _refine_one(self, request: RefineRequest) -> npt.NDArray[np.int64]:
        config = self.config
        observation = request.observation
        band = band_keys(observation.keys, config.band_keys_sq)
        unknown = np.setdiff1d(band, observation.keys, assume_unique=True)
        if unknown.size == 0 or observation.points.shape[0] < MIN_POINTS:
            return np.empty(0, dtype=np.int64)
        unknown = unknown[~sensor_empty(unknown, observation, config.camera, config.voxel_size, config.grid_offset)]
        if unknown.size == 0:
            return unknown
        mesh = self._reconstruct(observation.points.astype(np.float64), observation.point_origins())
        if mesh is None:
            return np.empty(0, dtype=np.int64)
        centres = key_centres(unpack_keys(unknown), config.voxel_size, config.grid_offset)
        return unknown[self._inside(mesh, centres)]

    def _reconstruct(self, points: npt.NDArray[np.float64], origins: npt.NDArray[np.float64]) -> Any | None:
        """The screened Poisson surface of the camera-oriented cloud, or None when it degenerates."""
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
        normals = np.asarray(cloud.normals)
        facing = np.einsum("ij,ij->i", normals, origins - points)
        normals[facing < 0] *= -1.0
        cloud.normals = o3d.utility.Vector3dVector(normals)
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=self.config.poisson_depth, scale=BOX_SCALE, linear_fit=False, n_threads=1
        )
        if len(mesh.triangles) == 0:
            return None
        return mesh

    def _inside(self, mesh: Any, centres: npt.NDArray[np.floating[Any]]) -> npt.NDArray[np.bool_]:
        """Whether each point is inside the reconstructed surface (ray parity in Open3D's scene)."""
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        query = o3d.core.Tensor(centres.astype(np.float32))
        occupancy = scene.compute_occupancy(query, nthreads=1)
        return occupancy.numpy().astype(bool)
