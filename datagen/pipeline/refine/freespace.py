"""Sensor-visible empty space, derived from an observation alone (no mesh).

Every observed point ends a ray from its camera: the space in front of it along that ray is empty.
A per-view depth buffer of the observed points (each splatted over the pixels its voxel covers)
answers, for any key, whether some view saw *past* it: a key whose centre lies in front of the
observed depth at its pixel by more than a voxel is empty. Keys no view saw past stay unknown.

A view's buffer depends on that view's points alone, and the multi-view cases of a task reuse its
single views, so `DepthBuffers` keeps them (by content) for a refiner to pass to `sensor_empty`.
Buffers are built and kept cropped to the pixels the points' splats reach (inf outside, as in the
full image), which changes no value.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.camera import Pose, look_at, project
from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, unpack_keys
from schemas.config import CameraConfig

SPLAT_VOXELS = math.sqrt(3) / 2


@dataclass(frozen=True)
class CroppedDepth:
    """A view's depth buffer within the pixel box its splats reach (rows v0.., columns u0..); inf outside."""

    depth: npt.NDArray[np.float32]
    v0: int
    u0: int
    pose: Pose

    def lookup(self, u: npt.NDArray[np.int64], v: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        """The depth at pixels (u, v) (inf outside the box; the caller keeps (u, v) inside the image)."""
        rows, cols = v - self.v0, u - self.u0
        height, width = self.depth.shape
        inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
        observed = np.full(u.size, np.inf)
        observed[inside] = self.depth[rows[inside], cols[inside]]
        return observed


def cropped_depth(
    observation: Observation, view: int, camera: CameraConfig, voxel_size: float, crop: bool = True
) -> CroppedDepth:
    """`depth_buffer` of one view, cropped to the pixels its points' splats reach (the whole image
    when ``crop`` is False)."""
    index = observation.views.index(view)
    pose = look_at(observation.origins[index])
    points = observation.points[observation.point_views == view].astype(np.float64)
    if points.size == 0:
        shape = (camera.height, camera.width) if not crop else (0, 0)
        return CroppedDepth(np.full(shape, np.inf, dtype=np.float32), 0, 0, pose)
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
    u0, v0, u1, v1 = 0, 0, camera.width, camera.height
    if crop:  # every pixel a splat below writes lies in this box
        u0, v0 = max(0, int(base_u.min()) - radius), max(0, int(base_v.min()) - radius)
        u1 = min(camera.width, int(base_u.max()) + radius + 1)
        v1 = min(camera.height, int(base_v.max()) + radius + 1)
    width, height = max(0, u1 - u0), max(0, v1 - v0)
    buffer = np.full(width * height, np.inf, dtype=np.float32)
    for du, dv in offsets:
        u, v = base_u + du, base_v + dv
        inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        np.minimum.at(buffer, (v[inside] - v0) * width + (u[inside] - u0), depth[inside])
    return CroppedDepth(buffer.reshape(height, width), v0, u0, pose)


def depth_buffer(
    observation: Observation, view: int, camera: CameraConfig, voxel_size: float
) -> tuple[npt.NDArray[np.float32], Pose]:
    """The nearest observed depth per pixel for one view of the observation (inf where none)."""
    whole = cropped_depth(observation, view, camera, voxel_size, crop=False)
    return whole.depth, whole.pose


class DepthBuffers:
    """Cropped depth buffers by content (a view's points, its origin, camera and voxel size), least
    recently used dropped past ``capacity`` (~0.5 MB each for an object 0.4 m from the camera)."""

    def __init__(self, capacity: int = 64) -> None:
        self.capacity = capacity
        self._buffers: OrderedDict[tuple[object, ...], CroppedDepth] = OrderedDict()

    def get(self, observation: Observation, view: int, camera: CameraConfig, voxel_size: float) -> CroppedDepth:
        key = (observation.view_digest(view), camera, float(voxel_size))
        found = self._buffers.get(key)
        if found is not None:
            self._buffers.move_to_end(key)
            return found
        crop = cropped_depth(observation, view, camera, voxel_size)
        self._buffers[key] = crop
        while len(self._buffers) > self.capacity:
            self._buffers.popitem(last=False)
        return crop


def sensor_empty(
    keys: npt.NDArray[np.int64],
    observation: Observation,
    camera: CameraConfig,
    voxel_size: float,
    grid_offset: tuple[float, float, float],
    buffers: DepthBuffers | None = None,
) -> npt.NDArray[np.bool_]:
    """For each packed key, whether some view of the observation saw empty space at its centre.

    ``buffers`` keeps cropped depth buffers and reuses those of views seen before (the same answer,
    computed once); without it every view's whole-image buffer is built afresh (the original code).
    """
    empty = np.zeros(keys.size, dtype=bool)
    if keys.size == 0:
        return empty
    centres = key_centres(unpack_keys(keys), voxel_size, grid_offset)
    for view in observation.views:
        if buffers is None:
            crop = cropped_depth(observation, view, camera, voxel_size, crop=False)
            empty |= _seen_past(crop, centres, camera, voxel_size)
            continue
        # A key one view saw empty stays empty: each view tests only the keys still undecided.
        undecided = np.flatnonzero(~empty)
        if undecided.size == 0:
            break
        crop = buffers.get(observation, view, camera, voxel_size)
        empty[undecided] = _seen_past(crop, centres[undecided], camera, voxel_size)
    return empty


def _seen_past(
    crop: CroppedDepth, centres: npt.NDArray[np.floating], camera: CameraConfig, voxel_size: float
) -> npt.NDArray[np.bool_]:
    """Whether the view of ``crop`` saw past each centre: it lies more than a voxel in front of the
    observed depth at its pixel (never for centres behind the camera or outside the image)."""
    local = crop.pose.world_to_camera(centres)
    uv = project(camera, local)
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (local[:, 2] > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    observed = np.full(centres.shape[0], np.inf)
    observed[inside] = crop.lookup(u[inside], v[inside])
    seen: npt.NDArray[np.bool_] = local[:, 2] < observed - voxel_size
    return seen
