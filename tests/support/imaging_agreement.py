"""What our imaging and an independent Open3D caster see of one real mesh (docs/pipeline.md sections 1.7 and 3).

Every mesh is prepared at size 0.15 m, rotation 0, and imaged in both modes from the 32 built-in
views; the reference (`open3d_reference`) rebuilds the same rays from the intrinsics and the view
positions and casts them with Open3D's RaycastingScene (float32). Shared by
``tests/pipeline/test_imaging_shared.py`` (the checks) and ``benchmarks/generation/imaging_agreement.py`` (the
table of measured numbers).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from datagen.pipeline.ground_truth import GroundTruth, sample_ground_truth
from datagen.pipeline.imaging import SPHERE_MARGIN, TaskImaging
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectOptions, mesh_file_spec
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig
from support.open3d_reference import (
    Intrinsics,
    Open3DCaster,
    image_pixels,
    image_targets,
    jaccard,
    pixel_rays,
    target_rays,
)

TARGETS = GenerationConfig(imaging="targets")
PIXELS = GenerationConfig(imaging="pixels")
MODES = {"targets": TARGETS, "pixels": PIXELS}
VIEW_SPACE = build_view_space(TARGETS.view_space)
SIZE_M = 0.15
HALF_DIAGONAL = np.sqrt(3.0) / 2.0 * TARGETS.voxel_size


@dataclass(frozen=True)
class ModeResult:
    ours: TaskImaging
    reference_keys: list[np.ndarray]
    reference_rays: list[int]
    jaccard: np.ndarray

    @property
    def union(self) -> np.ndarray:
        return np.unique(np.concatenate(self.ours.visible_keys()))

    def single_view_counts(self) -> np.ndarray:
        """Per view: how many of its keys no other view sees."""
        keys, counts = np.unique(np.concatenate(self.ours.visible_keys()), return_counts=True)
        only_one = keys[counts == 1]
        return np.array([np.isin(v, only_one, assume_unique=True).sum() for v in self.ours.visible_keys()])


@dataclass(frozen=True)
class MeshResult:
    name: str
    faces: int
    sampled: GroundTruth
    modes: dict[str, ModeResult]
    centre_distance: np.ndarray
    """Distance of every final P_gt key centre (pixels mode, a superset of targets') to the surface."""
    area: float
    """Surface area of the prepared mesh, m^2."""


@functools.cache
def mesh_result(path: Path) -> MeshResult:
    spec = mesh_file_spec(path, ObjectOptions(size=SIZE_M))
    prepared = prepare_object(spec, TARGETS)
    vertices = prepared.task_vertices(0, TARGETS.rotations)
    faces = prepared.faces
    sampled = sample_ground_truth(
        vertices,
        faces,
        TARGETS.voxel_size,
        TARGETS.grid_offset,
        TARGETS.gt_density,
        stream(TARGETS.seed, spec.object_id, 0, Purpose.GROUND_TRUTH),
    )
    camera = Intrinsics.of(TARGETS.camera)
    caster = Open3DCaster(vertices, faces)
    modes = {}
    for mode, config in MODES.items():
        ours = scan_task(prepared, 0, config, VIEW_SPACE)
        if mode == "targets":
            views = target_rays(camera, VIEW_SPACE.positions, ours.ground_truth.points)
            theirs = image_targets(
                caster,
                views,
                ours.ground_truth.points,
                config.voxel_size,
                config.grid_offset,
                camera.max_range,
            )
        else:
            radius = float(np.sqrt((vertices**2).sum(axis=1).max())) * (1.0 + SPHERE_MARGIN)
            views = pixel_rays(camera, VIEW_SPACE.positions, radius)
            theirs = image_pixels(caster, views, config.voxel_size, config.grid_offset, camera.max_range)
        scores = np.array([jaccard(a, b) for a, b in zip(ours.visible_keys(), theirs, strict=True)])
        modes[mode] = ModeResult(
            ours=ours,
            reference_keys=theirs,
            reference_rays=[v.directions.shape[0] for v in views],
            jaccard=scores,
        )
    final = modes["pixels"].ours.ground_truth
    centres = key_centres(unpack_keys(final.keys), TARGETS.voxel_size, TARGETS.grid_offset)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    closest, _, _ = trimesh.proximity.closest_point(mesh, centres)
    # the distance to a point trimesh returns on the surface bounds the true distance from above
    distance = np.linalg.norm(closest - centres, axis=1)
    return MeshResult(
        name=path.name, faces=len(faces), sampled=sampled, modes=modes, centre_distance=distance, area=float(mesh.area)
    )
