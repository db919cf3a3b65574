"""Camera (docs/pipeline.md section 2): look-at poses, projection, and the cropped pixel rays.

The cropped ray set is checked against an analytic truth computed here: every full-frame pixel whose
ray meets the sphere, by the ray-sphere discriminant.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from datagen.pipeline.camera import (
    ZENITH_FALLBACK_UP,
    full_frame_rays,
    inside_image,
    look_at,
    max_fitting_radius,
    project,
    sphere_pixel_rays,
)
from datagen.pipeline.viewspace import build_view_space
from schemas.config import CameraConfig, ViewSpaceConfig

CAMERA = CameraConfig()
BUILTIN = build_view_space(ViewSpaceConfig()).positions


def random_upper_positions(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    raw = rng.normal(size=(count, 3))
    raw[:, 2] = np.abs(raw[:, 2])
    return raw / np.linalg.norm(raw, axis=1, keepdims=True) * rng.uniform(0.2, 2.0, size=(count, 1))


def polar_degrees(position: np.ndarray) -> float:
    """Angle between the position and the zenith (world +z)."""
    return math.degrees(math.acos(abs(position[2]) / np.linalg.norm(position)))


# ------------------------------------------------------------------------------------------ look_at

POSITIONS = np.concatenate([BUILTIN, random_upper_positions(200, 0), [[0.3, -0.1, -0.2], [1.0, 0.0, 0.0]]])


@pytest.mark.parametrize("index", range(len(POSITIONS)), ids=lambda i: f"p{i}")
def test_look_at_is_a_right_handed_rotation_aimed_at_the_origin(index):
    position = POSITIONS[index]
    pose = look_at(position)
    rotation = pose.rotation
    np.testing.assert_array_equal(pose.origin, position)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    right, down, forward = rotation.T
    # x cross y = z: OpenCV's right-handed camera frame
    np.testing.assert_allclose(np.cross(right, down), forward, atol=1e-12)
    # the optical axis points at the origin
    np.testing.assert_allclose(forward, -position / np.linalg.norm(position), atol=1e-12)
    # the image x axis is horizontal: roll keeps world +z up (image up = -y)
    if polar_degrees(position) > 1.0:
        assert abs(right[2]) < 1e-12
        up_in_image = -down
        assert up_in_image[2] > 0
        # image up is world +z projected onto the image plane, normalised
        projected = np.array([0.0, 0.0, 1.0]) - forward * forward[2]
        np.testing.assert_allclose(up_in_image, projected / np.linalg.norm(projected), atol=1e-12)


@pytest.mark.parametrize("tilt_degrees", [0.0, 0.3, 0.99])
def test_look_at_near_the_zenith_uses_the_fallback_up(tilt_degrees):
    t = math.radians(tilt_degrees)
    position = 0.4 * np.array([math.sin(t) * 0.6, math.sin(t) * 0.8, math.cos(t)])
    pose = look_at(position)
    rotation = pose.rotation
    assert np.isfinite(rotation).all()
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    _, down, forward = rotation.T
    np.testing.assert_allclose(forward, -position / np.linalg.norm(position), atol=1e-12)
    # image up is the fallback (+y) projected onto the image plane
    fallback = ZENITH_FALLBACK_UP - forward * (forward @ ZENITH_FALLBACK_UP)
    np.testing.assert_allclose(-down, fallback / np.linalg.norm(fallback), atol=1e-12)
    assert -down[1] > 0


def test_look_at_just_outside_the_zenith_cone_uses_world_up():
    t = math.radians(1.01)
    position = 0.4 * np.array([math.sin(t), 0.0, math.cos(t)])
    right, down, _ = look_at(position).rotation.T
    assert abs(right[2]) < 1e-12
    assert -down[2] > 0
    # world +z up: the up vector leans toward +z and away from the camera (-x here)
    assert -down[0] < 0


def test_look_at_other_targets():
    target = np.array([0.1, -0.2, 0.05])
    position = np.array([0.5, 0.3, 0.4])
    pose = look_at(position, target)
    forward = pose.rotation[:, 2]
    np.testing.assert_allclose(forward, (target - position) / np.linalg.norm(target - position), atol=1e-12)
    uv = project(CAMERA, pose.world_to_camera(target[None, :]))
    np.testing.assert_allclose(uv[0], [CAMERA.cx, CAMERA.cy], atol=1e-9)


# ---------------------------------------------------------------------------------------- projection


@pytest.mark.parametrize("index", range(0, 32, 3))
def test_points_on_the_optical_axis_project_to_the_principal_point(index):
    position = BUILTIN[index]
    pose = look_at(position)
    along_axis = position[None, :] * np.array([[0.9], [0.5], [0.0], [-0.3], [-1.0]])  # depths 0.04..0.8
    camera_points = pose.world_to_camera(along_axis)
    np.testing.assert_allclose(camera_points[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(camera_points[:, 2], np.linalg.norm(position - along_axis, axis=1), atol=1e-12)
    uv = project(CAMERA, camera_points)
    np.testing.assert_allclose(uv, np.tile([CAMERA.cx, CAMERA.cy], (5, 1)), atol=1e-9)
    assert inside_image(CAMERA, uv, camera_points[:, 2]).all()


def test_world_up_appears_above_and_world_right_to_the_right():
    pose = look_at(BUILTIN[5])
    right = pose.rotation[:, 0]
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], right * 0.01])
    uv = project(CAMERA, pose.world_to_camera(points))
    assert uv[1, 1] < uv[0, 1]  # higher in the world = smaller v (image rows go down)
    assert uv[2, 0] > uv[0, 0]


def test_projection_is_the_pinhole_formula():
    camera = CameraConfig(width=200, height=100, fx=150.0, fy=140.0, cx=90.0, cy=60.0)
    points = np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 1.0], [-1.0, 0.5, 4.0]])
    expected = np.array([[90 + 150 * 0.05, 60 - 140 * 0.1], [90.0, 60.0], [90 - 150 * 0.25, 60 + 140 * 0.125]])
    np.testing.assert_allclose(project(camera, points), expected, atol=1e-12)


def test_inside_image_bounds():
    camera = CameraConfig(width=200, height=100, fx=150.0, fy=140.0, cx=90.0, cy=60.0)
    uv = np.array([[0.0, 0.0], [199.999, 99.999], [200.0, 50.0], [50.0, 100.0], [-1e-9, 5.0], [5.0, 5.0]])
    depth = np.array([1.0, 1.0, 1.0, 1.0, 1.0, -1.0])
    np.testing.assert_array_equal(inside_image(camera, uv, depth), [True, True, False, False, False, False])


def test_full_frame_rays_go_through_pixel_centres():
    pose = look_at(BUILTIN[11])
    directions, pixels = full_frame_rays(CAMERA, pose)
    assert directions.shape == (CAMERA.width * CAMERA.height, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    sample = np.random.default_rng(1).choice(len(directions), 5000, replace=False)
    uv = project(CAMERA, pose.world_to_camera(pose.origin + directions[sample]))
    np.testing.assert_allclose(uv, pixels[sample].astype(np.float64), atol=1e-6)
    frac = pixels - np.floor(pixels)
    np.testing.assert_array_equal(frac, 0.5)
    assert {tuple(p) for p in np.floor(pixels[[0, -1]]).astype(int)} == {(0, 0), (1279, 719)}


# ------------------------------------------------------------------------------ cropped pixel rays


def analytic_sphere_pixels(origin: np.ndarray, directions: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels whose ray (t > 0) meets the origin-centred sphere, and a mask of rays within rounding of
    the rim (where either answer is correct)."""
    b = directions @ origin
    c = float(origin @ origin) - radius * radius
    discriminant = b * b - c
    meets = (discriminant >= 0) & (b < 0)
    ambiguous = np.abs(discriminant) <= 1e-12 * float(origin @ origin)
    return meets, ambiguous


def pixel_set(pixels: np.ndarray) -> set[tuple[int, int]]:
    return set(map(tuple, np.floor(pixels).astype(np.int64).tolist()))


@pytest.mark.parametrize(
    ("view", "radius_factor"),
    [(0, 0.5), (7, 1.0), (19, 0.999999), (31, 0.2), (4, 1.25), (12, 2.5)],
)
def test_sphere_pixel_rays_equal_the_full_frame_pixels_that_meet_the_sphere(view, radius_factor):
    pose = look_at(BUILTIN[view])
    radius = max_fitting_radius(CAMERA, 0.4) * radius_factor  # > 1: the sphere is clipped by the frame
    directions, pixels = sphere_pixel_rays(CAMERA, pose, radius)

    full_dirs, full_pixels = full_frame_rays(CAMERA, pose)
    meets, ambiguous = analytic_sphere_pixels(pose.origin, full_dirs, radius)
    assert ambiguous.sum() <= 2
    expected = pixel_set(full_pixels[meets & ~ambiguous])
    got = pixel_set(pixels)
    assert len(got) == len(pixels), "a pixel is listed twice"
    allowed = expected | pixel_set(full_pixels[ambiguous])
    assert expected <= got, f"{len(expected - got)} pixels that meet the sphere are missing"
    assert got <= allowed, f"{len(got - allowed)} pixels miss the sphere"
    assert len(got) > 1000

    # directions are the unit rays through those pixel centres
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
    index = np.floor(pixels[:, 1]).astype(np.int64) * CAMERA.width + np.floor(pixels[:, 0]).astype(np.int64)
    np.testing.assert_allclose(directions, full_dirs[index], atol=1e-12)
    np.testing.assert_array_equal(pixels, full_pixels[index])


def test_sphere_pixel_rays_count_is_close_to_the_projected_disc_area():
    # The sphere's image is (nearly) an ellipse of semi-axes fx*tan(a), fy*tan(a) with sin(a) = r/d.
    pose = look_at(BUILTIN[3])
    radius = 0.075
    directions, _ = sphere_pixel_rays(CAMERA, pose, radius)
    half_angle = math.asin(radius / 0.4)
    area = math.pi * CAMERA.fx * CAMERA.fy * math.tan(half_angle) ** 2
    assert abs(len(directions) - area) / area < 0.02


def test_sphere_pixel_rays_refuse_a_camera_inside_the_sphere():
    with pytest.raises(ValueError, match="inside the bounding sphere"):
        sphere_pixel_rays(CAMERA, look_at(BUILTIN[0]), 0.5)


# ---------------------------------------------------------------------------------- fitting radius


@pytest.mark.parametrize("distance", [0.4, 0.25, 1.0])
def test_max_fitting_radius_is_the_largest_sphere_every_view_sees_whole(distance):
    radius = max_fitting_radius(CAMERA, distance)
    # silhouette directions of a sphere of radius r at the origin, seen from (0, 0, -distance) in the
    # camera frame: the cone of half-angle asin(r / distance) around the optical axis
    angles = np.linspace(0.0, 2 * math.pi, 20000, endpoint=False)

    def silhouette(r: float) -> np.ndarray:
        half = math.asin(r / distance)
        return np.stack(
            [
                math.sin(half) * np.cos(angles),
                math.sin(half) * np.sin(angles),
                np.full_like(angles, math.cos(half)),
            ],
            axis=1,
        )

    inside = silhouette(radius * (1 - 1e-9))
    uv = project(CAMERA, inside)
    assert inside_image(CAMERA, uv, inside[:, 2]).all()
    outside = silhouette(radius * 1.001)
    uv = project(CAMERA, outside)
    assert not inside_image(CAMERA, uv, outside[:, 2]).all()
    # with the default intrinsics the limit is set by the bottom edge: (height - cy) / fy
    expected = distance * math.sin(math.atan((CAMERA.height - CAMERA.cy) / CAMERA.fy))
    assert radius == pytest.approx(expected, rel=1e-12)
