"""Imaging (docs/pipeline.md section 3) on an icosphere, against truths computed here.

- Exact first hits: brute-force Möller–Trumbore in float64 over every face of the mesh.
- Hit counts: the analytic ray-sphere discriminant. The icosphere is convex and lies between its
  inscribed sphere (radius = smallest face-plane distance) and its circumscribed sphere (= largest
  vertex norm), so a ray meeting the inscribed sphere must hit and a ray missing the circumscribed
  one must miss: count_in <= hits <= count_out, exactly. For subdivisions=6 the two radii differ by
  7e-6 relative, so both counts are within 0.02 % of the count for the nominal radius 0.05 m.
- The crop: a full-frame cast of every pixel with the same caster must give the same hits.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import trimesh

from datagen.pipeline.camera import full_frame_rays, inside_image, look_at, project, sphere_pixel_rays
from datagen.pipeline.ground_truth import GroundTruth, sample_ground_truth
from datagen.pipeline.imaging import SPHERE_MARGIN, Observation, image_task
from datagen.pipeline.keys import points_to_keys, points_to_packed
from datagen.pipeline.objects.prepare import PreparedObject
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.raycast import RayCaster
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

RADIUS = 0.05
TOLERANCE_M = 1e-6
BARYCENTRIC_BAND = 1e-4
"""Rays passing within this barycentric margin of a triangle's edge may be hit or missed by Embree's
float32 test (float32 rounding of a 0.4 m ray is ~3e-8 m; triangle edges here are ~1 mm)."""

TARGETS = GenerationConfig(imaging="targets")
PIXELS = GenerationConfig(imaging="pixels")
VIEW_SPACE = build_view_space(TARGETS.view_space)
SPEC = ObjectSpec(
    source="test:icosphere",
    name="icosphere",
    options=ObjectOptions(),
    object_id=hashlib.sha256(b"icosphere subdivisions=6 radius=0.05").hexdigest(),
)


# ------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=6, radius=RADIUS)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    plane = np.einsum("ij,ij->i", normals, vertices[faces[:, 0]]) / np.linalg.norm(normals, axis=1)
    return {
        "vertices": vertices,
        "faces": faces,
        "r_in": float(plane.min()),
        "r_out": float(np.linalg.norm(vertices, axis=1).max()),
    }


@pytest.fixture(scope="module")
def prepared(sphere):
    return PreparedObject(
        spec=SPEC,
        vertices=sphere["vertices"],
        faces=sphere["faces"],
        units_guessed="m",
        scale=1.0,
        size=2 * RADIUS,
        watertight=True,
    )


@pytest.fixture(scope="module")
def sampled_gt(sphere) -> GroundTruth:
    rng = stream(TARGETS.seed, SPEC.object_id, 0, Purpose.GROUND_TRUTH)
    return sample_ground_truth(
        sphere["vertices"], sphere["faces"], TARGETS.voxel_size, TARGETS.grid_offset, TARGETS.gt_density, rng
    )


@pytest.fixture(scope="module")
def caster(sphere) -> RayCaster:
    return RayCaster(sphere["vertices"], sphere["faces"])


@pytest.fixture(scope="module")
def targets_run(sphere, sampled_gt, caster):
    return image_task(sphere["vertices"], sphere["faces"], sampled_gt, VIEW_SPACE, TARGETS, caster)


@pytest.fixture(scope="module")
def pixels_run(sphere, sampled_gt, caster):
    return image_task(sphere["vertices"], sphere["faces"], sampled_gt, VIEW_SPACE, PIXELS, caster)


# ------------------------------------------------------------------------------ independent truths


def brute_force_first_hits(
    origin: np.ndarray, directions: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Exact nearest intersection of each ray with any face (Möller–Trumbore, float64, all faces).

    Returns (t, margin): t is inf for a miss; margin is the largest min-barycentric over the faces
    whose plane the ray crosses in front of the origin, so |margin| < band flags rays that graze an
    edge of the silhouette, where a float32 tracer may legitimately decide either way.
    """
    o = np.asarray(origin, dtype=np.float64)
    v0 = vertices[faces[:, 0]]
    e1 = vertices[faces[:, 1]] - v0
    e2 = vertices[faces[:, 2]] - v0
    s = o - v0  # (F, 3): the origin is shared by every ray of a view
    q = np.cross(s, e1)  # (F, 3)
    # With p = d x e2: det = e1.p = -d.(e1 x e2), u = s.p / det = d.(e2 x s) / det,
    # v = d.q / det, t = e2.q / det. Only the dot products with d depend on the ray.
    minus_normal = -np.cross(e1, e2)
    e2_cross_s = np.cross(e2, s)
    t_numerator = np.einsum("ij,ij->i", e2, q)
    t_out = np.full(directions.shape[0], np.inf)
    margin_out = np.full(directions.shape[0], -np.inf)
    for start in range(0, directions.shape[0], chunk):
        d = directions[start : start + chunk]
        det = d @ minus_normal.T
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / det
            u = (d @ e2_cross_s.T) * inverse
            v = (d @ q.T) * inverse
            t = t_numerator[None, :] * inverse
        valid = np.isfinite(inverse) & (t > 0)
        margin = np.minimum(np.minimum(u, v), 1.0 - u - v)
        inside = valid & (margin >= 0)
        t_hit = np.where(inside, t, np.inf).min(axis=1)
        t_out[start : start + chunk] = t_hit
        margin_out[start : start + chunk] = np.where(valid, margin, -np.inf).max(axis=1)
    return t_out, margin_out


def rays_meeting_sphere(origin: np.ndarray, directions: np.ndarray, radius: float) -> np.ndarray:
    """Rays (t > 0) meeting the origin-centred sphere: discriminant of |o + t d|^2 = r^2."""
    b = directions @ origin
    return (b * b - (origin @ origin - radius * radius) >= 0) & (b < 0)


def pixel_index(pixels: np.ndarray, width: int) -> np.ndarray:
    return np.floor(pixels[:, 1]).astype(np.int64) * width + np.floor(pixels[:, 0]).astype(np.int64)


def compare_with_brute_force(origin, directions, distance, sphere):
    """Assert that caster distances agree with the exact first hits; returns (hits, ambiguous)."""
    exact_t, margin = brute_force_first_hits(origin, directions, sphere["vertices"], sphere["faces"])
    ambiguous = np.abs(margin) < BARYCENTRIC_BAND
    ours_hit = np.isfinite(distance)
    exact_hit = np.isfinite(exact_t)
    disagree = (ours_hit != exact_hit) & ~ambiguous
    assert not disagree.any(), f"{disagree.sum()} rays hit/miss differently from the exact answer"
    both = ours_hit & exact_hit
    ours_points = origin + directions[both] * distance[both, None]
    exact_points = origin + directions[both] * exact_t[both, None]
    error = np.linalg.norm(ours_points - exact_points, axis=1)
    assert error.max(initial=0.0) <= TOLERANCE_M, f"hit off by {error.max():.3g} m"
    return ours_hit, ambiguous


# ------------------------------------------------------------------ (a) exact hits, both modes


def test_brute_force_reference_is_right_on_a_single_triangle():
    """The reference itself: a hand-checked triangle, hit inside, missed outside, nearest of two."""
    vertices = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2], [1, 0, 2], [0, 1, 2]], dtype=float)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    origin = np.zeros(3)
    directions = np.array([[0.25, 0.25, 1.0], [0.6, 0.6, 1.0], [0.0, 0.0, -1.0], [0.1, 0.7, 1.0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    t, _ = brute_force_first_hits(origin, directions, vertices, faces)
    hit_z = (directions[:, 2] * t)[[0, 3]]
    np.testing.assert_allclose(hit_z, 1.0, atol=1e-15)
    assert np.isinf(t[1]) and np.isinf(t[2])


def test_pixels_hits_are_the_exact_first_hits(sphere, pixels_run):
    """Sampled pixel rays of several views: whether each ray hits (its pixel is in the observation)
    and where (the observation's point) agree with brute force over all faces."""
    rng = np.random.default_rng(11)
    radius = sphere["r_out"] * (1 + SPHERE_MARGIN)
    checked_hits = 0
    for view in (0, 9, 21, 30):
        pose = look_at(VIEW_SPACE.positions[view])
        directions, pixels = sphere_pixel_rays(PIXELS.camera, pose, radius)
        observation = pixels_run.observations[view]
        observed = {tuple(p): i for i, p in enumerate(observation.pixels.tolist())}
        # uniform over the crop, plus every crop ray that misses the inscribed sphere (the rim
        # between the two silhouettes, where a ray may miss)
        rim = np.flatnonzero(~rays_meeting_sphere(pose.origin, directions, sphere["r_in"]))
        chosen = np.union1d(rng.choice(directions.shape[0], 75, replace=False), rim)
        distance = np.full(chosen.size, np.inf)
        for j, index in enumerate(chosen):
            row = observed.get(tuple(pixels[index].tolist()))
            if row is not None:
                distance[j] = np.linalg.norm(observation.points[row].astype(np.float64) - pose.origin)
        hit, ambiguous = compare_with_brute_force(pose.origin, directions[chosen], distance, sphere)
        checked_hits += int((hit & ~ambiguous).sum())
    assert checked_hits >= 250, checked_hits


def test_caster_first_hits_are_exact_over_the_full_frame(sphere, caster):
    """Random full-frame rays (mostly misses) and rays aimed at the rim: RayCaster vs brute force."""
    rng = np.random.default_rng(5)
    pose = look_at(VIEW_SPACE.positions[13])
    directions, _ = full_frame_rays(PIXELS.camera, pose)
    near = rays_meeting_sphere(pose.origin, directions, sphere["r_out"] * 1.001)
    rim = near & ~rays_meeting_sphere(pose.origin, directions, sphere["r_in"] * 0.999)
    chosen = np.concatenate([rng.choice(directions.shape[0], 100, replace=False), rng.choice(np.flatnonzero(rim), 100)])
    distance, primitive = caster.first_hits(pose.origin, directions[chosen], PIXELS.camera.max_range)
    assert ((primitive >= 0) == np.isfinite(distance)).all()
    hit, _ = compare_with_brute_force(pose.origin, directions[chosen], distance, sphere)
    assert hit.sum() >= 30 and (~hit).sum() >= 30


def test_caster_respects_the_range(sphere, caster):
    pose = look_at(VIEW_SPACE.positions[2])
    directions = -pose.origin[None, :] / np.linalg.norm(pose.origin)
    distance, primitive = caster.first_hits(pose.origin, directions, 0.4 - RADIUS + 1e-3)
    assert distance[0] == pytest.approx(0.4 - RADIUS, abs=1e-5) and primitive[0] >= 0
    distance, primitive = caster.first_hits(pose.origin, directions, 0.4 - RADIUS - 1e-3)
    assert np.isinf(distance[0]) and primitive[0] == -1
    empty_distance, empty_primitive = caster.first_hits(pose.origin, np.empty((0, 3)), 1.0)
    assert empty_distance.shape == (0,) and empty_primitive.shape == (0,)


def in_image_targets(gt: GroundTruth, view: int):
    """Indices of the P_gt points that project inside the image of a view, and the pose."""
    pose = look_at(VIEW_SPACE.positions[view])
    camera_points = pose.world_to_camera(gt.points)
    uv = project(TARGETS.camera, camera_points)
    return np.flatnonzero(inside_image(TARGETS.camera, uv, camera_points[:, 2])), pose


def test_targets_hits_are_the_exact_first_hits(sphere, sampled_gt, targets_run, caster):
    """Sampled P_gt targets: the first hit along the ray to each is exact, and the key is visible
    exactly when that exact first hit lies in the target's key."""
    rng = np.random.default_rng(3)
    visible_checked = hidden_checked = 0
    for view in (1, 14, 27):
        candidates, pose = in_image_targets(sampled_gt, view)
        chosen = rng.choice(candidates, 120, replace=False)
        offsets = sampled_gt.points[chosen] - pose.origin
        directions = offsets / np.linalg.norm(offsets, axis=1, keepdims=True)
        distance, _ = caster.first_hits(pose.origin, directions, TARGETS.camera.max_range)
        compare_with_brute_force(pose.origin, directions, distance, sphere)

        exact_t, _ = brute_force_first_hits(pose.origin, directions, sphere["vertices"], sphere["faces"])
        exact_points = pose.origin + directions * exact_t[:, None]
        exact_visible = (
            points_to_packed(exact_points, TARGETS.voxel_size, TARGETS.grid_offset) == (sampled_gt.keys[chosen])
        )
        observation = targets_run.observations[view]
        reported = np.isin(sampled_gt.keys[chosen], observation.keys)
        np.testing.assert_array_equal(reported, exact_visible)
        # the observation's point for a visible key is the exact hit
        rows = np.searchsorted(observation.keys, sampled_gt.keys[chosen][reported])
        error = np.linalg.norm(observation.points[rows].astype(np.float64) - exact_points[reported], axis=1)
        assert error.max(initial=0.0) <= TOLERANCE_M
        visible_checked += int(reported.sum())
        hidden_checked += int((~reported).sum())
    assert visible_checked >= 100 and hidden_checked >= 100, (visible_checked, hidden_checked)


def test_targets_visibility_on_a_convex_mesh(sphere, sampled_gt, targets_run):
    """On a convex mesh, a point facing the camera (clearly, not at the silhouette) is its own first
    hit, so its key is visible; a point clearly facing away is hidden behind the front side."""
    for view in range(0, 32, 5):
        candidates, pose = in_image_targets(sampled_gt, view)
        points = sampled_gt.points[candidates]
        to_camera = pose.origin - points
        facing = np.einsum("ij,ij->i", points / RADIUS, to_camera / np.linalg.norm(to_camera, axis=1)[:, None])
        visible = np.isin(sampled_gt.keys[candidates], targets_run.observations[view].keys)
        assert visible[facing > 0.05].all()
        assert not visible[facing < -0.05].any()


# ------------------------------------------------------------------- (b) hit counts vs the sphere


def test_pixels_hit_count_matches_the_analytic_sphere(sphere, pixels_run):
    crop_radius = sphere["r_out"] * (1 + SPHERE_MARGIN)
    for view, observation in enumerate(pixels_run.observations):
        pose = look_at(VIEW_SPACE.positions[view])
        directions, _ = full_frame_rays(PIXELS.camera, pose)
        # the crop is every pixel whose ray meets the bounding sphere (a rim ray may go either way)
        crop = rays_meeting_sphere(pose.origin, directions, crop_radius)
        rim = crop & ~rays_meeting_sphere(pose.origin, directions, crop_radius * (1 - 1e-12))
        assert 0 <= crop.sum() - pixels_run.per_view_rays[view] <= rim.sum(), view
        hits = observation.points.shape[0]
        count_in = int(rays_meeting_sphere(pose.origin, directions, sphere["r_in"]).sum())
        count_out = int(rays_meeting_sphere(pose.origin, directions, sphere["r_out"]).sum())
        nominal = int(rays_meeting_sphere(pose.origin, directions, RADIUS).sum())
        assert count_in <= hits <= count_out, (view, count_in, hits, count_out)
        assert abs(hits - nominal) <= 0.01 * nominal
        assert hits > 30000  # a 5 cm sphere at 0.4 m covers ~36k pixels


# ------------------------------------------------------------------ (c) crop == full frame


@pytest.mark.parametrize("view", [0, 17, 31])
def test_cropped_cast_equals_full_frame_cast(caster, pixels_run, view):
    pose = look_at(VIEW_SPACE.positions[view])
    directions, pixels = full_frame_rays(PIXELS.camera, pose)
    distance, _ = caster.first_hits(pose.origin, directions, PIXELS.camera.max_range)
    hit = np.isfinite(distance)
    full_points = pose.origin + directions[hit] * distance[hit, None]
    full_index = pixel_index(pixels[hit], PIXELS.camera.width)

    observation = pixels_run.observations[view]
    crop_index = pixel_index(observation.pixels, PIXELS.camera.width)
    assert np.unique(crop_index).size == crop_index.size
    order = np.argsort(crop_index)
    np.testing.assert_array_equal(crop_index[order], full_index)  # full_index is ascending
    np.testing.assert_allclose(observation.points[order], full_points, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(
        observation.keys, np.unique(points_to_packed(full_points, PIXELS.voxel_size, PIXELS.grid_offset))
    )


# ------------------------------------------------------------------ (d) keys and P_gt


def near_voxel_face(points: np.ndarray, config: GenerationConfig, slack: float) -> np.ndarray:
    """Points whose scaled coordinates lie within ``slack`` voxels of a voxel boundary."""
    scaled = np.asarray(points, dtype=np.float64) / config.voxel_size + np.asarray(config.grid_offset)
    return (np.abs(scaled - np.round(scaled)) < slack).any(axis=1)


FLOAT32_SLACK = 1e-5
"""A float32 point near 0.05 m is rounded by up to ~4e-9 m = 2e-6 voxels."""


def test_ground_truth_is_consistent(sphere, sampled_gt):
    assert len(sampled_gt) == sampled_gt.sampled
    assert (np.diff(sampled_gt.keys) > 0).all()
    # each representative point lies in its key, and on the sphere
    np.testing.assert_array_equal(
        points_to_packed(sampled_gt.points, TARGETS.voxel_size, TARGETS.grid_offset), sampled_gt.keys
    )
    norms = np.linalg.norm(sampled_gt.points, axis=1)
    assert norms.min() >= sphere["r_in"] * (1 - 1e-12) and norms.max() <= sphere["r_out"] * (1 + 1e-12)
    # area-weighted sampling at 256 per voxel face area leaves no surface voxel unsampled: on a 5 cm
    # sphere that is about 4 pi r^2 / vs^2 * 1.5 (mean chord of a cube) = ~11.8k keys
    assert 9_000 < len(sampled_gt) < 15_000


def test_targets_keys_are_sorted_unique_subsets_of_ground_truth(targets_run, sampled_gt):
    assert targets_run.ground_truth is sampled_gt or np.array_equal(targets_run.ground_truth.keys, sampled_gt.keys)
    union = []
    for view, observation in enumerate(targets_run.observations):
        keys = observation.keys
        assert keys.dtype == np.int64
        assert (np.diff(keys) > 0).all()
        assert np.isin(keys, sampled_gt.keys).all()
        assert observation.views == (view,)
        n = keys.size
        assert observation.points.shape == (n, 3) and observation.points.dtype == np.float32
        assert observation.pixels.shape == (n, 2) and observation.point_views.shape == (n,)
        assert (observation.point_views == view).all()
        np.testing.assert_array_equal(observation.origins, VIEW_SPACE.positions[view][None, :])
        # each point (float32) keys to its key; only a point within float32 rounding of a voxel face
        # may key differently
        point_keys = points_to_packed(observation.points, TARGETS.voxel_size, TARGETS.grid_offset)
        differ = point_keys != keys
        assert not (differ & ~near_voxel_face(observation.points, TARGETS, FLOAT32_SLACK)).any()
        # each point is where its pixel says
        pose = look_at(VIEW_SPACE.positions[view])
        uv = project(TARGETS.camera, pose.world_to_camera(observation.points))
        np.testing.assert_allclose(uv, observation.pixels, atol=2e-3)
        union.append(keys)
        assert n > 3000
    # half the sphere is seen from each view; together the 32 views see the upper part
    assert np.unique(np.concatenate(union)).size > 0.6 * len(sampled_gt)
    assert targets_run.rays_cast == sum(targets_run.per_view_rays)


def test_pixels_ground_truth_holds_every_hit_key(pixels_run, sampled_gt):
    final = pixels_run.ground_truth
    assert final.sampled == sampled_gt.sampled <= len(final)
    assert (np.diff(final.keys) > 0).all()
    all_hit_keys = []
    for view, observation in enumerate(pixels_run.observations):
        assert (np.diff(observation.keys) > 0).all()
        assert np.isin(observation.keys, final.keys).all()
        assert (observation.point_views == view).all()
        point_keys = points_to_packed(observation.points, PIXELS.voxel_size, PIXELS.grid_offset)
        fine = ~near_voxel_face(observation.points, PIXELS, FLOAT32_SLACK)
        assert np.isin(point_keys[fine], observation.keys).all()
        # every key comes from some point (one keyed across a face by float32 rounding excepted)
        assert (~np.isin(observation.keys, point_keys)).sum() <= (~fine).sum()
        all_hit_keys.append(observation.keys)
    hit_keys = np.unique(np.concatenate(all_hit_keys))
    # P_gt = sampled keys united with hit keys, nothing else
    np.testing.assert_array_equal(final.keys, np.union1d(sampled_gt.keys, hit_keys))
    added = ~np.isin(final.keys, sampled_gt.keys)
    assert added.sum() == len(final) - final.sampled
    # the sampled keys keep their points; an added key's point is a hit inside it
    np.testing.assert_array_equal(final.points[~added], sampled_gt.points)
    np.testing.assert_array_equal(
        points_to_packed(final.points[added], PIXELS.voxel_size, PIXELS.grid_offset), final.keys[added]
    )
    # dense sampling leaves few keys only imaging finds
    assert added.sum() <= 0.01 * hit_keys.size


def test_with_hits_is_a_union_with_first_hit_points():
    base = GroundTruth(keys=np.array([2, 5, 9]), points=np.array([[0.0, 0, 2], [0, 0, 5], [0, 0, 9]]), sampled=3)
    hit_keys = np.array([7, 5, 1, 7, 1])
    hit_points = np.array([[1.0, 0, 7], [1, 0, 5], [1, 0, 1], [2, 0, 7], [2, 0, 1]])
    merged = base.with_hits(hit_keys, hit_points)
    np.testing.assert_array_equal(merged.keys, [1, 2, 5, 7, 9])
    np.testing.assert_array_equal(merged.points[:, 0], [1, 0, 0, 1, 0])
    assert merged.sampled == 3 and len(merged) == 5
    assert base.with_hits(np.array([5, 9]), np.zeros((2, 3))) is base


# ------------------------------------------------------------------ (e) Observation.combine


def test_combine_concatenates_in_view_order_and_unites_keys(pixels_run):
    parts = [pixels_run.observations[i] for i in (7, 0, 3)]
    combined = Observation.combine(parts)
    assert combined.views == (0, 3, 7)
    assert combined.mask == (1 << 0) | (1 << 3) | (1 << 7)
    ordered = [pixels_run.observations[i] for i in (0, 3, 7)]
    np.testing.assert_array_equal(combined.points, np.concatenate([o.points for o in ordered]))
    np.testing.assert_array_equal(combined.pixels, np.concatenate([o.pixels for o in ordered]))
    np.testing.assert_array_equal(
        combined.point_views, np.repeat([0, 3, 7], [o.points.shape[0] for o in ordered]).astype(np.uint8)
    )
    np.testing.assert_array_equal(combined.origins, VIEW_SPACE.positions[[0, 3, 7]])
    expected_keys = np.union1d(np.union1d(ordered[0].keys, ordered[1].keys), ordered[2].keys)
    np.testing.assert_array_equal(combined.keys, expected_keys)
    assert combined.keys.size < sum(o.keys.size for o in ordered)  # overlapping views share keys
    # point_origins: each point's own camera centre
    np.testing.assert_array_equal(combined.point_origins(), VIEW_SPACE.positions[combined.point_views])


def test_combining_combinations_equals_the_flat_combination(pixels_run):
    parts = [pixels_run.observations[i] for i in (7, 0, 3)]
    flat = Observation.combine(parts)
    nested = Observation.combine([Observation.combine(parts[:2]), parts[2]])
    np.testing.assert_array_equal(nested.keys, flat.keys)
    assert nested.views == flat.views == (0, 3, 7)
    np.testing.assert_array_equal(nested.point_views, flat.point_views)
    np.testing.assert_array_equal(nested.points, flat.points)


def test_combine_refuses_a_view_twice(targets_run):
    a = targets_run.observations[4]
    with pytest.raises(ValueError, match="more than one"):
        Observation.combine([a, Observation.combine([a, targets_run.observations[5]])])


def test_single_observation_accessors(targets_run):
    observation = targets_run.observations[12]
    assert observation.mask == 1 << 12
    origins = observation.point_origins()
    assert origins.shape == (observation.points.shape[0], 3)
    np.testing.assert_array_equal(origins, np.tile(VIEW_SPACE.positions[12], (origins.shape[0], 1)))
    assert targets_run.visible_keys()[12] is observation.keys


def test_point_origins_of_high_views():
    observation = Observation(
        views=(2, 63),
        origins=np.array([[1.0, 2, 3], [4, 5, 6]]),
        points=np.zeros((3, 3), dtype=np.float32),
        point_views=np.array([63, 2, 63], dtype=np.uint8),
        pixels=np.zeros((3, 2), dtype=np.float32),
        keys=np.array([1, 2]),
    )
    np.testing.assert_array_equal(observation.point_origins(), [[4, 5, 6], [1, 2, 3], [4, 5, 6]])
    assert observation.mask == (1 << 2) | (1 << 63)


# ------------------------------------------------------------------ (f) determinism


def assert_same_imaging(a, b):
    np.testing.assert_array_equal(a.ground_truth.keys, b.ground_truth.keys)
    np.testing.assert_array_equal(a.ground_truth.points, b.ground_truth.points)
    assert a.ground_truth.sampled == b.ground_truth.sampled
    assert a.per_view_rays == b.per_view_rays and a.rays_cast == b.rays_cast
    assert len(a.observations) == len(b.observations) == VIEW_SPACE.count
    for x, y in zip(a.observations, b.observations, strict=True):
        assert x.views == y.views
        for name in ("origins", "points", "point_views", "pixels", "keys"):
            left, right = getattr(x, name), getattr(y, name)
            assert left.dtype == right.dtype, name
            np.testing.assert_array_equal(left, right, err_msg=name)


@pytest.mark.parametrize("config", [TARGETS, PIXELS], ids=["targets", "pixels"])
def test_scan_task_is_deterministic(prepared, config):
    first = scan_task(prepared, 0, config, VIEW_SPACE)
    second = scan_task(prepared, 0, config, VIEW_SPACE)
    assert_same_imaging(first, second)
    # and it is sensitive: another rotation (or seed) gives another P_gt
    other = scan_task(prepared, 1, config, VIEW_SPACE)
    assert not np.array_equal(other.ground_truth.points, first.ground_truth.points)
    reseeded = scan_task(prepared, 0, config.model_copy(update={"seed": 1}), VIEW_SPACE)
    assert not np.array_equal(reseeded.ground_truth.points, first.ground_truth.points)


def test_scan_task_equals_its_steps(prepared, sampled_gt, targets_run):
    scanned = scan_task(prepared, 0, TARGETS, VIEW_SPACE)
    assert targets_run.ground_truth is sampled_gt
    assert_same_imaging(scanned, targets_run)


def test_scan_task_rejects_a_rotation_out_of_range(prepared):
    with pytest.raises(ValueError, match="outside"):
        scan_task(prepared, TARGETS.rotations, TARGETS, VIEW_SPACE)


def test_points_to_keys_next_to_a_voxel_corner():
    """Keys are computed in float64: a point 1e-12 m past a voxel corner keys into that voxel."""
    offset = np.asarray(TARGETS.grid_offset)
    face = (np.array([10.0, -3.0, 7.0]) - offset) * TARGETS.voxel_size  # on a voxel corner
    nudged = face + np.array([1e-12, 1e-12, 1e-12])
    np.testing.assert_array_equal(points_to_keys(nudged[None, :], TARGETS.voxel_size, offset), [[10, -3, 7]])
