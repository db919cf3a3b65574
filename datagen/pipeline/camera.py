"""Pinhole camera and look-at poses (docs/pipeline.md section 2).

Camera frame follows OpenCV: x right, y down, z forward (the optical axis, through the origin). The
roll keeps world +z up in the image; within 1 degree of the zenith, where that is undefined, world +y
serves as the up vector instead (a fixed, documented fallback).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from schemas.config import CameraConfig

WORLD_UP = np.array([0.0, 0.0, 1.0])
ZENITH_FALLBACK_UP = np.array([0.0, 1.0, 0.0])
ZENITH_TOLERANCE_DEG = 1.0


@dataclass(frozen=True)
class Pose:
    """Camera-to-world rotation (columns: camera x, y, z in world) and the camera centre.

    Its transforms are tall-skinny matmuls: call them with BLAS bounded to one thread
    (`datagen.pipeline.thread_limits.single_threaded_blas`), which is up to 100x faster with OpenBLAS on 2 cores.
    """

    rotation: npt.NDArray[np.float64]
    origin: npt.NDArray[np.float64]

    def world_to_camera(self, points: npt.ArrayLike) -> npt.NDArray[np.float64]:
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation

    def camera_to_world_dirs(self, directions: npt.ArrayLike) -> npt.NDArray[np.float64]:
        return np.asarray(directions, dtype=np.float64) @ self.rotation.T


def look_at(position: npt.ArrayLike, target: npt.ArrayLike = (0.0, 0.0, 0.0)) -> Pose:
    """Pose at ``position`` whose optical axis passes through ``target``."""
    origin = np.asarray(position, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - origin
    forward /= np.linalg.norm(forward)
    up = WORLD_UP
    if abs(float(forward @ WORLD_UP)) > math.cos(math.radians(ZENITH_TOLERANCE_DEG)):
        up = ZENITH_FALLBACK_UP
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return Pose(rotation=np.stack([right, down, forward], axis=1), origin=origin)


def project(camera: CameraConfig, points_camera: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Continuous pixel coordinates (u, v) of camera-frame points; pixel (i, j) spans [i, i+1)."""
    p = np.asarray(points_camera, dtype=np.float64)
    z = p[:, 2]
    return np.stack([camera.fx * p[:, 0] / z + camera.cx, camera.fy * p[:, 1] / z + camera.cy], axis=1)


def inside_image(camera: CameraConfig, uv: npt.NDArray[np.float64], depth: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Points in front of the camera that project inside the image rectangle."""
    return (
        (np.asarray(depth) > 0)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] < camera.width)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < camera.height)
    )


def inscribed_half_angle(camera: CameraConfig) -> float:
    """Half-angle (radians) of the largest cone around the optical axis that stays inside the image."""
    return min(
        math.atan(camera.cx / camera.fx),
        math.atan((camera.width - camera.cx) / camera.fx),
        math.atan(camera.cy / camera.fy),
        math.atan((camera.height - camera.cy) / camera.fy),
    )


def max_fitting_radius(camera: CameraConfig, view_distance: float) -> float:
    """Largest bounding-sphere radius (centred on the optical axis) that every view sees whole."""
    return view_distance * math.sin(inscribed_half_angle(camera))


def sphere_pixel_rays(
    camera: CameraConfig, pose: Pose, radius: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32]]:
    """Unit world directions and pixel centres of every pixel whose ray meets the sphere of ``radius``
    around the origin (the view looks at the origin)."""
    directions, pixels = cone_pixel_rays(camera, float(np.linalg.norm(pose.origin)), radius)
    return pose.camera_to_world_dirs(directions), pixels


def cone_pixel_rays(
    camera: CameraConfig, distance: float, radius: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32]]:
    """Camera-frame unit directions and pixel centres of the pixels whose ray meets a sphere of
    ``radius`` centred on the optical axis at ``distance``.

    The same for every view at that distance, so a task computes it once. Only the pixel box of
    the sphere's projection is enumerated (a few percent of the frame), and inside it only pixels
    whose direction lies in the sphere's cone are kept, so the result equals a full-frame cast hit
    for hit.
    """
    if radius >= distance:
        raise ValueError("the camera is inside the bounding sphere")
    half_angle = math.asin(radius / distance)
    cos_cone, tan_cone = math.cos(half_angle), math.tan(half_angle)
    margin = 1.0
    u_lo = max(0, math.floor(camera.cx - camera.fx * tan_cone - margin))
    u_hi = min(camera.width, math.ceil(camera.cx + camera.fx * tan_cone + margin))
    v_lo = max(0, math.floor(camera.cy - camera.fy * tan_cone - margin))
    v_hi = min(camera.height, math.ceil(camera.cy + camera.fy * tan_cone + margin))
    uu, vv = np.meshgrid(np.arange(u_lo, u_hi) + 0.5, np.arange(v_lo, v_hi) + 0.5)
    x = (uu.ravel() - camera.cx) / camera.fx
    y = (vv.ravel() - camera.cy) / camera.fy
    inv_norm = 1.0 / np.sqrt(x * x + y * y + 1.0)
    keep = inv_norm >= cos_cone  # the z component of the unit direction is the cosine to the axis
    directions = np.stack([x[keep], y[keep], np.ones(int(keep.sum()))], axis=1) * inv_norm[keep, None]
    pixels = np.stack([uu.ravel()[keep], vv.ravel()[keep]], axis=1).astype(np.float32)
    return directions, pixels


def full_frame_rays(camera: CameraConfig, pose: Pose) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32]]:
    """Every pixel's unit world direction (for tests that check the crop against the full frame)."""
    uu, vv = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    x = (uu.ravel() - camera.cx) / camera.fx
    y = (vv.ravel() - camera.cy) / camera.fy
    dirs = np.stack([x, y, np.ones_like(x)], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float32)
    return pose.camera_to_world_dirs(dirs), pixels
