"""Virtual imaging of one task from every candidate view (docs/pipeline.md section 3).

Two modes share one ray caster:

- ``targets`` (the authors' semantics): one ray from the camera centre toward each P_gt
  representative point that projects inside the image; the key is visible when the first hit lies
  in that same key. Independent of image resolution.
- ``pixels`` (a depth camera): one ray through the centre of every pixel whose ray can meet the
  object's bounding sphere; the first hits, keyed. P_gt is then united with every key hit.

An `Observation` carries what a refiner needs besides the points: the view of every point and each
view's camera centre, so the sensor-visible empty space (camera-to-hit segments) can be derived.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from datagen.pipeline.camera import Pose, cone_pixel_rays, inside_image, look_at, max_fitting_radius, project
from datagen.pipeline.ground_truth import GroundTruth
from datagen.pipeline.keys import KeyGrid, union_keys, unpack_keys
from datagen.pipeline.raycast import RayCaster
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.pipeline.viewspace import ViewSpace
from schemas.config import GenerationConfig

SPHERE_MARGIN = 1e-9
"""Relative growth of the bounding sphere so that rays grazing its rim are still cast."""


@dataclass(frozen=True)
class Observation:
    """What a set of views saw: one row per hit point, plus the unique keys.

    ``views`` is sorted; ``origins[j]`` is the camera centre of ``views[j]``; ``point_views[i]`` is
    the view id of point i. ``keys`` are packed (see `datagen.pipeline.keys`), sorted and unique.
    """

    views: tuple[int, ...]
    origins: npt.NDArray[np.float64]
    points: npt.NDArray[np.float32]
    point_views: npt.NDArray[np.uint8]
    pixels: npt.NDArray[np.float32]
    keys: npt.NDArray[np.int64]

    @property
    def mask(self) -> int:
        """The case as an n-bit mask (bit i = view i)."""
        value = 0
        for view in self.views:
            value |= 1 << view
        return value

    def view_digest(self, view: int) -> bytes:
        """A digest of one view's part (its id, camera centre and points): equal for the same view's
        data in a single-view observation and in any case that holds it, so caches can key on it."""
        points = np.ascontiguousarray(self.points[self.point_views == view])
        origin = np.ascontiguousarray(self.origins[self.views.index(view)], dtype=np.float64)
        digest = hashlib.blake2b(digest_size=16)
        for part in (np.int64(view).tobytes(), origin.tobytes(), str(points.dtype).encode(), points.tobytes()):
            digest.update(part)
        return digest.digest()

    def point_origins(self) -> npt.NDArray[np.float64]:
        """Camera centre of each point's view: the start of its sensor ray."""
        lookup = np.zeros((max(self.views) + 1, 3))
        lookup[list(self.views)] = self.origins
        return lookup[self.point_views]

    @staticmethod
    def combine(observations: Sequence[Observation]) -> Observation:
        """O_S for a case S: the views' observations concatenated (in view order), keys united."""
        ordered = sorted(observations, key=lambda o: min(o.views))
        origin_of = {v: o.origins[j] for o in ordered for j, v in enumerate(o.views)}
        if sum(len(o.views) for o in ordered) != len(origin_of):
            raise ValueError("a view appears in more than one observation")
        views = tuple(sorted(origin_of))
        point_views = np.concatenate([o.point_views for o in ordered])
        rows = np.argsort(point_views, kind="stable")  # rows in view order, each view's own order kept
        return Observation(
            views=views,
            origins=np.stack([origin_of[v] for v in views]),
            points=np.concatenate([o.points for o in ordered])[rows],
            point_views=point_views[rows],
            pixels=np.concatenate([o.pixels for o in ordered])[rows],
            keys=union_keys(*(o.keys for o in ordered)),
        )


@dataclass(frozen=True)
class TaskImaging:
    """The 32 (n) single-view observations of one task and the final P_gt."""

    observations: tuple[Observation, ...]
    ground_truth: GroundTruth
    rays_cast: int
    seconds: float
    per_view_rays: tuple[int, ...] = field(default=())

    def visible_keys(self) -> list[npt.NDArray[np.int64]]:
        """V_i for every view i."""
        return [o.keys for o in self.observations]


def view_poses(view_space: ViewSpace) -> list[Pose]:
    return [look_at(position) for position in view_space.positions]


def image_task(
    vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    ground_truth: GroundTruth,
    view_space: ViewSpace,
    config: GenerationConfig,
    caster: RayCaster | None = None,
) -> TaskImaging:
    """Image the task's mesh (already in the task frame) from every view."""
    started = time.perf_counter()
    with single_threaded_blas():
        caster = caster or RayCaster(vertices, faces)
        poses = view_poses(view_space)
        if config.imaging == "targets":
            observations, rays = _image_targets(caster, ground_truth, poses, config)
            final_gt = ground_truth
        else:
            observations, rays, new_keys, new_points = _image_pixels(caster, vertices, ground_truth, poses, config)
            final_gt = ground_truth.with_hits(new_keys, new_points)
    return TaskImaging(
        observations=tuple(observations),
        ground_truth=final_gt,
        rays_cast=int(sum(rays)),
        seconds=time.perf_counter() - started,
        per_view_rays=tuple(rays),
    )


def _image_targets(
    caster: RayCaster, gt: GroundTruth, poses: Sequence[Pose], config: GenerationConfig
) -> tuple[list[Observation], list[int]]:
    observations, rays = [], []
    radius = float(np.sqrt(np.einsum("ij,ij->i", gt.points, gt.points).max())) if len(gt) else 0.0
    everything = np.arange(len(gt))
    grid = KeyGrid.around(gt.points, config.voxel_size, config.grid_offset)
    gt_cells = grid.linear_of_keys(unpack_keys(gt.keys))
    for view, pose in enumerate(poses):
        distance_to_centre = float(np.linalg.norm(pose.origin))
        if radius <= max_fitting_radius(config.camera, distance_to_centre):
            candidates = everything  # the sphere holding P_gt projects inside the image
        else:
            camera_points = pose.world_to_camera(gt.points)
            uv = project(config.camera, camera_points)
            candidates = np.flatnonzero(inside_image(config.camera, uv, camera_points[:, 2]))
        if distance_to_centre + radius <= config.camera.max_range:
            offsets = (gt.points if candidates is everything else gt.points[candidates]) - pose.origin
        else:
            offsets = gt.points[candidates] - pose.origin
            within = np.einsum("ij,ij->i", offsets, offsets) <= config.camera.max_range**2
            candidates, offsets = candidates[within], offsets[within]
        # Rays along the unnormalised offsets: the target sits at t = 1, and the first hit anywhere
        # on the way is at t <= 1 (Embree and the float64 refinement both accept any direction length).
        hit, distance, _, hit_directions = caster.cast(pose.origin, offsets, np.inf)
        hit_points = pose.origin + hit_directions * distance[:, None]
        # A hit may land outside the box of P_gt's representative points only when it is not in
        # the target's key; clip so that it still gets a cell number (it compares unequal anyway).
        hit_cells = grid.linear_of_points(hit_points, config.voxel_size, config.grid_offset, clip=True)
        same_key = hit_cells == gt_cells[candidates[hit]]
        visible = candidates[hit[same_key]]
        # candidates are in P_gt order (sorted keys), so visible keys come out sorted and unique.
        observations.append(
            Observation(
                views=(view,),
                origins=pose.origin[None, :].copy(),
                points=hit_points[same_key].astype(np.float32),
                point_views=np.full(visible.size, view, dtype=np.uint8),
                pixels=project(config.camera, pose.world_to_camera(gt.points[visible])).astype(np.float32),
                keys=gt.keys[visible],
            )
        )
        rays.append(int(candidates.size))
    return observations, rays


def _image_pixels(
    caster: RayCaster,
    vertices: npt.NDArray[np.float64],
    gt: GroundTruth,
    poses: Sequence[Pose],
    config: GenerationConfig,
) -> tuple[list[Observation], list[int], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Observations, rays per view, and the hit keys P_gt lacks with their first hit point
    (in view, then pixel order)."""
    radius = float(np.sqrt(np.einsum("ij,ij->i", vertices, vertices).max())) * (1.0 + SPHERE_MARGIN)
    grid = KeyGrid.around(vertices, config.voxel_size, config.grid_offset)
    in_gt = np.zeros(grid.size, dtype=bool)
    in_gt[grid.linear_of_keys(unpack_keys(gt.keys))] = True
    ray_tables: dict[float, tuple[npt.NDArray[np.float64], npt.NDArray[np.float32]]] = {}
    observations, rays = [], []
    new_cells, new_points = [], []
    for view, pose in enumerate(poses):
        distance_to_centre = round(float(np.linalg.norm(pose.origin)), 9)
        if distance_to_centre not in ray_tables:
            ray_tables[distance_to_centre] = cone_pixel_rays(config.camera, distance_to_centre, radius)
        camera_directions, pixels = ray_tables[distance_to_centre]
        directions = pose.camera_to_world_dirs(camera_directions)
        hit, distance, _, hit_directions = caster.cast(pose.origin, directions, config.camera.max_range)
        hit_points = pose.origin + hit_directions * distance[:, None]
        cells = grid.linear_of_points(hit_points, config.voxel_size, config.grid_offset)
        unseen = np.flatnonzero(~in_gt[cells])
        new_cells.append(cells[unseen])
        new_points.append(hit_points[unseen])
        observations.append(
            Observation(
                views=(view,),
                origins=pose.origin[None, :].copy(),
                points=hit_points.astype(np.float32),
                point_views=np.full(hit.size, view, dtype=np.uint8),
                pixels=pixels[hit],
                keys=grid.packed_of(grid.unique(cells)),
            )
        )
        rays.append(int(directions.shape[0]))
    cells = np.concatenate(new_cells)
    return observations, rays, grid.packed_of(cells), np.concatenate(new_points)
