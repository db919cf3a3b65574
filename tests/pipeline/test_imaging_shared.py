"""Imaging of the real meshes of ../shared/meshes, cross-checked against Open3D (PIPELINE.md 1.7, 3).

Every mesh is prepared at size 0.15 m, rotation 0, and imaged in both modes from the 32 built-in
views. The independent reference (`open3d_reference`) rebuilds the same rays from the intrinsics
and the view positions and casts them with Open3D's RaycastingScene (float32), so per-view key sets
must agree up to float32 rounding at voxel faces and silhouettes.

Run with ``-rP`` (or ``-s``) to see the measured numbers table printed by the last test.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import requires_shared_meshes, shared_mesh_paths
from support.open3d_reference import (
    Intrinsics,
    Open3DCaster,
    image_pixels,
    image_targets,
    jaccard,
    pixel_rays,
    target_rays,
)

from datagen.pipeline.ground_truth import GroundTruth, sample_ground_truth
from datagen.pipeline.imaging import SPHERE_MARGIN, TaskImaging
from datagen.pipeline.keys import key_centres, points_to_packed, unpack_keys
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, file_object_id
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

pytestmark = requires_shared_meshes

TARGETS = GenerationConfig(imaging="targets")
PIXELS = GenerationConfig(imaging="pixels")
MODES = {"targets": TARGETS, "pixels": PIXELS}
VIEW_SPACE = build_view_space(TARGETS.view_space)
SIZE_M = 0.15
HALF_DIAGONAL = np.sqrt(3.0) / 2.0 * TARGETS.voxel_size

MESHES = shared_mesh_paths()
MESH_IDS = [p.name for p in MESHES]


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


@functools.cache
def mesh_result(path: Path) -> MeshResult:
    options = ObjectOptions(size=SIZE_M)
    spec = ObjectSpec(
        source=str(path),
        name=path.stem,
        options=options,
        object_id=file_object_id(path.read_bytes(), options),
    )
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
    return MeshResult(name=path.name, faces=len(faces), sampled=sampled, modes=modes, centre_distance=distance)


mesh_parameters = pytest.mark.parametrize("path", MESHES, ids=MESH_IDS)


@mesh_parameters
def test_ground_truth_sampling_is_the_one_imaging_used(path):
    result = mesh_result(path)
    targets_gt = result.modes["targets"].ours.ground_truth
    # targets mode never adds keys: its P_gt is the pure sampling
    np.testing.assert_array_equal(targets_gt.keys, result.sampled.keys)
    np.testing.assert_array_equal(targets_gt.points, result.sampled.points)
    assert result.sampled.sampled == len(result.sampled)
    np.testing.assert_array_equal(
        points_to_packed(result.sampled.points, TARGETS.voxel_size, TARGETS.grid_offset), result.sampled.keys
    )
    pixels_gt = result.modes["pixels"].ours.ground_truth
    assert pixels_gt.sampled == len(result.sampled) <= len(pixels_gt)
    assert np.isin(result.sampled.keys, pixels_gt.keys).all()


@mesh_parameters
@pytest.mark.parametrize("mode", list(MODES))
def test_open3d_casts_the_same_rays(path, mode):
    result = mesh_result(path).modes[mode]
    assert tuple(result.reference_rays) == result.ours.per_view_rays


@mesh_parameters
@pytest.mark.parametrize("mode", list(MODES))
def test_visibility_agrees_with_open3d(path, mode):
    scores = mesh_result(path).modes[mode].jaccard
    assert scores.size == VIEW_SPACE.count
    worst = int(np.argmin(scores))
    assert scores.min() >= 0.99, f"view {worst}: Jaccard {scores[worst]:.5f}"
    assert scores.mean() >= 0.999, f"mean Jaccard {scores.mean():.5f}"


@mesh_parameters
@pytest.mark.parametrize("mode", list(MODES))
def test_union_of_views_has_a_plausible_size(path, mode):
    result = mesh_result(path).modes[mode]
    union = result.union
    assert 400 <= union.size <= 20_000, union.size
    assert np.isin(union, result.ours.ground_truth.keys).all()


@mesh_parameters
def test_pixels_sampled_ground_truth_holds_99_percent_of_what_imaging_sees(path):
    result = mesh_result(path)
    union = result.modes["pixels"].union
    fraction = np.isin(union, result.sampled.keys).mean()
    assert fraction >= 0.99, f"sampled P_gt holds {fraction:.4f} of the pixels union"


@mesh_parameters
def test_every_ground_truth_key_centre_lies_near_the_surface(path):
    result = mesh_result(path)
    distance = result.centre_distance
    assert distance.size == len(result.modes["pixels"].ours.ground_truth)
    worst = float(distance.max())
    assert worst <= HALF_DIAGONAL * (1 + 1e-9), f"a key centre is {worst / TARGETS.voxel_size:.4f} voxels away"


@mesh_parameters
def test_targets_keys_seen_by_one_view_only_are_rare(path):
    counts = mesh_result(path).modes["targets"].single_view_counts()
    assert np.median(counts) <= 10, counts


def test_print_measured_numbers():
    """Not a check: the table of measured numbers (shown with -rP or -s)."""
    header = (
        f"{'mesh':20} {'faces':>7} {'P_gt':>6} {'U tgt':>6} {'U pix':>6} {'pix smp%':>8} "
        f"{'J tgt min/mean':>16} {'J pix min/mean':>16} {'1-view med tgt/pix':>18} {'dmax/vox':>8}"
    )
    lines = [header]
    for path in MESHES:
        r = mesh_result(path)
        t, p = r.modes["targets"], r.modes["pixels"]
        fraction = 100 * np.isin(p.union, r.sampled.keys).mean()
        lines.append(
            f"{path.name:20} {r.faces:7d} {len(r.sampled):6d} {t.union.size:6d} {p.union.size:6d} {fraction:8.2f} "
            f"{t.jaccard.min():7.5f}/{t.jaccard.mean():8.6f} {p.jaccard.min():7.5f}/{p.jaccard.mean():8.6f} "
            f"{np.median(t.single_view_counts()):9.1f}/{np.median(p.single_view_counts()):8.1f} "
            f"{r.centre_distance.max() / TARGETS.voxel_size:8.4f}"
        )
    print("\n" + "\n".join(lines))
