"""Sensor-visible empty space, derived from an observation alone (no mesh).

Every observed point ends a ray from its camera: the space in front of it along that ray is empty.
A per-view depth buffer of the observed points (each splatted over the pixels its voxel covers)
answers, for any key, whether some view saw *past* it: a key whose centre lies in front of the
observed depth at its pixel by more than a voxel is empty. Keys no view saw past stay unknown.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from datagen.pipeline.camera import Pose, look_at, project
from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, unpack_keys
from schemas.config import CameraConfig

SPLAT_VOXELS = math.sqrt(3) / 2


def depth_buffer(
    observation: Observation, view: int, camera: CameraConfig, voxel_size: float
) -> tuple[npt.NDArray[np.float32], Pose]:
    """The nearest observed depth per pixel for one view of the observation (inf where none)."""
    index = observation.views.index(view)
    pose = look_at(observation.origins[index])
    points = observation.points[observation.point_views == view].astype(np.float64)
    buffer = np.full(camera.width * camera.height, np.inf, dtype=np.float32)
    if points.size == 0:
        return buffer.reshape(camera.height, camera.width), pose
    local = pose.world_to_camera(points)
    uv = project(camera, local)
    depth = local[:, 2].astype(np.float32)
    # Splat over the voxel's full footprint (half its diagonal, sqrt(3)/2 voxel), so neighbouring
    # points' discs overlap and no deeper point shows through a gap in front of a nearer surface.
    radius = max(0, math.ceil(SPLAT_VOXELS * camera.fx * voxel_size / float(depth.min())))
    span = range(-radius, radius + 1)
    offsets = [(du, dv) for du in span for dv in span if du * du + dv * dv <= radius * radius]
    base_u = np.floor(uv[:, 0]).astype(np.int64)
    base_v = np.floor(uv[:, 1]).astype(np.int64)
    for du, dv in offsets:
        u, v = base_u + du, base_v + dv
        inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        np.minimum.at(buffer, v[inside] * camera.width + u[inside], depth[inside])
    return buffer.reshape(camera.height, camera.width), pose


def sensor_empty(
    keys: npt.NDArray[np.int64],
    observation: Observation,
    camera: CameraConfig,
    voxel_size: float,
    grid_offset: tuple[float, float, float],
) -> npt.NDArray[np.bool_]:
    """For each packed key, whether some view of the observation saw empty space at its centre."""
    empty = np.zeros(keys.size, dtype=bool)
    if keys.size == 0:
        return empty
    centres = key_centres(unpack_keys(keys), voxel_size, grid_offset)
    for view in observation.views:
        buffer, pose = depth_buffer(observation, view, camera, voxel_size)
        local = pose.world_to_camera(centres)
        uv = project(camera, local)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (local[:, 2] > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        observed = np.full(keys.size, np.inf)
        observed[inside] = buffer[v[inside], u[inside]]
        empty |= local[:, 2] < observed - voxel_size
    return empty
