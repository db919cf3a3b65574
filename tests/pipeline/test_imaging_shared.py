"""Imaging of the real meshes of ../shared/meshes, cross-checked against Open3D (docs/pipeline.md sections 1.7 and 3).

Every mesh is prepared at size 0.15 m, rotation 0, and imaged in both modes from the 32 built-in
views. The independent reference (`open3d_reference`) rebuilds the same rays from the intrinsics
and the view positions and casts them with Open3D's RaycastingScene (float32), so per-view key sets
must agree up to float32 rounding at voxel faces and silhouettes.

The table of measured numbers: ``python -m benchmarks.generation.imaging_agreement``.
"""

from __future__ import annotations

import numpy as np
import pytest
from support.imaging_agreement import HALF_DIAGONAL, MODES, TARGETS, VIEW_SPACE, mesh_result
from support.meshes import requires_shared_meshes, shared_mesh_paths

from datagen.pipeline.keys import points_to_packed

pytestmark = requires_shared_meshes

MESHES = shared_mesh_paths()
MESH_IDS = [p.name for p in MESHES]

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
    # A surface of area A meets at most about sqrt(3) * A / s^2 voxels of side s (a plane at the worst
    # angle; curvature and edges add little at this resolution): a union past 2 * A / s^2 means keys
    # off the surface or a wrong scale, whatever the mesh.
    surface_cells = mesh_result(path).area / TARGETS.voxel_size**2
    assert 400 <= union.size <= 2.0 * surface_cells, (union.size, surface_cells)
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
    """The 32 views overlap: in the median view at most 1 % of the keys are seen by no other view
    (deep pockets such as a gear's tooth gaps make a few views private, never the typical one)."""
    result = mesh_result(path).modes["targets"]
    counts = result.single_view_counts()
    sizes = np.array([keys.size for keys in result.ours.visible_keys()])
    private = counts / np.maximum(sizes, 1)
    assert np.median(private) <= 0.01, private
