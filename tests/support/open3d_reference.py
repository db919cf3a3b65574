"""An independent reference for imaging (docs/pipeline.md section 3), built on Open3D's RaycastingScene.

Used by the tests (to cross-check `datagen.pipeline.imaging` view by view) and by ``benchmarks/generation/imaging.py``
(to time Open3D on exactly the rays our imaging casts). Nothing here calls the code under test except
`datagen.pipeline.keys.pack_keys`, the bijection from integer key triples to the packed int64 scalars that
both sides' key sets are compared in.

- Poses: look-at toward the origin, OpenCV axes (x right, y down, z forward), roll keeping world +z
  up in the image, world +y as the up vector within 1 degree of the zenith.
- ``pixels``: a pixel's ray meets the origin-centred sphere of radius r seen from distance d exactly
  when its normalised image coordinates (x, y) satisfy x^2 + y^2 <= r^2 / (d^2 - r^2) (the sphere's
  tangent cone around the optical axis). One ray per such pixel centre; the first hits, keyed.
- ``targets``: one ray from the camera centre toward every ground-truth point that projects inside
  the image (pinhole, in front of the camera); the point's key is visible when the first hit lies in
  that same key.

Open3D casts in float32 (origins, directions, vertices) and returns the float32 distance ``t_hit``;
hit points are formed in float64 as ``origin + direction * t_hit``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import open3d as o3d

from datagen.pipeline.keys import pack_keys

ZENITH_DEGREES = 1.0


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    max_range: float

    @classmethod
    def of(cls, camera: object) -> Intrinsics:
        """From any object with the camera fields (e.g. `schemas.config.CameraConfig`)."""
        return cls(
            width=int(camera.width),  # type: ignore[attr-defined]
            height=int(camera.height),  # type: ignore[attr-defined]
            fx=float(camera.fx),  # type: ignore[attr-defined]
            fy=float(camera.fy),  # type: ignore[attr-defined]
            cx=float(camera.cx),  # type: ignore[attr-defined]
            cy=float(camera.cy),  # type: ignore[attr-defined]
            max_range=float(camera.max_range),  # type: ignore[attr-defined]
        )


@dataclass(frozen=True)
class ViewRays:
    """The rays of one view: one origin, unit float64 directions, and for ``targets`` the index of
    the ground-truth point each ray aims at."""

    origin: npt.NDArray[np.float64]
    directions: npt.NDArray[np.float64]
    targets: npt.NDArray[np.int64] | None = None
    pixels: npt.NDArray[np.float64] | None = None

    def as_open3d(self) -> o3d.core.Tensor:
        """The (N, 6) float32 ray tensor Open3D takes: origin then direction."""
        rays = np.empty((self.directions.shape[0], 6), dtype=np.float32)
        rays[:, :3] = self.origin.astype(np.float32)
        rays[:, 3:] = self.directions.astype(np.float32)
        return o3d.core.Tensor(rays)


def camera_rotation(position: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Camera-to-world rotation (columns right, down, forward) of a camera at ``position`` aimed at
    the origin."""
    p = np.asarray(position, dtype=np.float64)
    forward = -p / math.sqrt(float(p @ p))
    up = np.array([0.0, 0.0, 1.0])
    if math.degrees(math.acos(min(1.0, abs(float(forward[2]))))) < ZENITH_DEGREES:
        up = np.array([0.0, 1.0, 0.0])
    right = np.array(
        [
            forward[1] * up[2] - forward[2] * up[1],
            forward[2] * up[0] - forward[0] * up[2],
            forward[0] * up[1] - forward[1] * up[0],
        ]
    )
    right /= math.sqrt(float(right @ right))
    down = np.array(
        [
            forward[1] * right[2] - forward[2] * right[1],
            forward[2] * right[0] - forward[0] * right[2],
            forward[0] * right[1] - forward[1] * right[0],
        ]
    )
    return np.stack([right, down, forward], axis=1)


def sphere_pixels(camera: Intrinsics, distance: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame unit directions and pixel centres (u, v) of the pixels whose ray meets a sphere
    of ``radius`` centred on the optical axis at ``distance``."""
    limit_sq = radius * radius / (distance * distance - radius * radius)
    limit = math.sqrt(limit_sq)
    u0 = max(0, math.floor(camera.cx - camera.fx * limit) - 2)
    u1 = min(camera.width, math.ceil(camera.cx + camera.fx * limit) + 2)
    v0 = max(0, math.floor(camera.cy - camera.fy * limit) - 2)
    v1 = min(camera.height, math.ceil(camera.cy + camera.fy * limit) + 2)
    v, u = np.mgrid[v0:v1, u0:u1]
    u = u.ravel() + 0.5
    v = v.ravel() + 0.5
    x = (u - camera.cx) / camera.fx
    y = (v - camera.cy) / camera.fy
    keep = x * x + y * y <= limit_sq
    x, y = x[keep], y[keep]
    directions = np.stack([x, y, np.ones_like(x)], axis=1)
    directions /= np.sqrt((directions**2).sum(axis=1))[:, None]
    return directions, np.stack([u[keep], v[keep]], axis=1)


def pixel_rays(camera: Intrinsics, positions: npt.ArrayLike, radius: float) -> list[ViewRays]:
    """``pixels`` mode: the rays of every pixel that can meet the origin-centred sphere of ``radius``."""
    out = []
    for position in np.asarray(positions, dtype=np.float64):
        rotation = camera_rotation(position)
        local, pixels = sphere_pixels(camera, float(np.linalg.norm(position)), radius)
        out.append(ViewRays(origin=position.copy(), directions=local @ rotation.T, pixels=pixels))
    return out


def target_rays(camera: Intrinsics, positions: npt.ArrayLike, points: npt.ArrayLike) -> list[ViewRays]:
    """``targets`` mode: a ray toward every point in front of the camera that projects inside the
    image (pixel (i, j) spans [i, i+1) x [j, j+1))."""
    world = np.asarray(points, dtype=np.float64)
    out = []
    for position in np.asarray(positions, dtype=np.float64):
        rotation = camera_rotation(position)
        offsets = world - position
        local = offsets @ rotation  # rows: coordinates along right, down, forward
        depth = local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = camera.fx * local[:, 0] / depth + camera.cx
            v = camera.fy * local[:, 1] / depth + camera.cy
        inside = (depth > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        targets = np.flatnonzero(inside)
        chosen = offsets[targets]
        directions = chosen / np.sqrt((chosen**2).sum(axis=1))[:, None]
        out.append(
            ViewRays(
                origin=position.copy(),
                directions=directions,
                targets=targets,
                pixels=np.stack([u[targets], v[targets]], axis=1),
            )
        )
    return out


def voxel_keys(points: npt.ArrayLike, voxel_size: float, grid_offset: Sequence[float]) -> np.ndarray:
    """Packed keys of float64 points: floor(p / voxel_size + offset) per axis."""
    p = np.asarray(points, dtype=np.float64)
    integer = np.floor(p / voxel_size + np.asarray(grid_offset, dtype=np.float64)).astype(np.int64)
    return pack_keys(integer)


class Open3DCaster:
    """First hits with Open3D's RaycastingScene (float32 Embree inside Open3D)."""

    def __init__(self, vertices: npt.ArrayLike, faces: npt.ArrayLike) -> None:
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
        )

    def cast_raw(self, rays: o3d.core.Tensor, nthreads: int = 0) -> dict:
        """Open3D's own call, nothing around it (what the benchmark times)."""
        return self.scene.cast_rays(rays, nthreads=nthreads)

    def distances(self, view: ViewRays, max_range: float, nthreads: int = 0) -> np.ndarray:
        """float64 distance to the first hit along each ray, inf where none within ``max_range``."""
        if view.directions.shape[0] == 0:
            return np.empty(0)
        t = self.cast_raw(view.as_open3d(), nthreads)["t_hit"].numpy().astype(np.float64)
        t[~(t <= max_range)] = np.inf
        return t

    def hit_points(self, view: ViewRays, max_range: float, nthreads: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Mask of rays that hit, and their float64 hit points."""
        t = self.distances(view, max_range, nthreads)
        hit = np.isfinite(t)
        return hit, view.origin + view.directions[hit] * t[hit, None]


def image_pixels(
    caster: Open3DCaster,
    views: Sequence[ViewRays],
    voxel_size: float,
    grid_offset: Sequence[float],
    max_range: float,
    nthreads: int = 0,
) -> list[np.ndarray]:
    """V_i of ``pixels`` mode: sorted unique packed keys of every first hit, per view."""
    out = []
    for view in views:
        _, points = caster.hit_points(view, max_range, nthreads)
        out.append(np.unique(voxel_keys(points, voxel_size, grid_offset)))
    return out


def image_targets(
    caster: Open3DCaster,
    views: Sequence[ViewRays],
    points: npt.ArrayLike,
    voxel_size: float,
    grid_offset: Sequence[float],
    max_range: float,
    nthreads: int = 0,
) -> list[np.ndarray]:
    """V_i of ``targets`` mode: keys of the target points whose ray's first hit lies in their key."""
    target_keys = voxel_keys(points, voxel_size, grid_offset)
    out = []
    for view in views:
        assert view.targets is not None
        hit, hit_points = caster.hit_points(view, max_range, nthreads)
        aimed = target_keys[view.targets]
        same = np.zeros(hit.size, dtype=bool)
        same[hit] = voxel_keys(hit_points, voxel_size, grid_offset) == aimed[hit]
        out.append(np.unique(aimed[same]))
    return out


def jaccard(a: np.ndarray, b: np.ndarray) -> float:
    union = np.union1d(a, b).size
    return 1.0 if union == 0 else np.intersect1d(a, b).size / union
