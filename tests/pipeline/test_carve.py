"""The carve refiner and sensor-visible empty space, against an analytic sphere."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datagen.pipeline.ground_truth import sample_ground_truth
from datagen.pipeline.imaging import image_task
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.refine import RefineRequest, band_keys, make_refiner
from datagen.pipeline.refine.freespace import sensor_empty
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

RADIUS = 0.05


@pytest.fixture(scope="module", params=["targets", "pixels"])
def sphere_scan(request: pytest.FixtureRequest):  # type: ignore[no-untyped-def]
    config = GenerationConfig(imaging=request.param, refiner="carve")
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    gt = sample_ground_truth(
        mesh.vertices, mesh.faces, config.voxel_size, config.grid_offset, 64.0, np.random.default_rng(0)
    )
    scan = image_task(mesh.vertices, mesh.faces, gt, build_view_space(config.view_space), config)
    return config, scan


def centres(config: GenerationConfig, keys: np.ndarray) -> np.ndarray:
    return key_centres(unpack_keys(keys), config.voxel_size, config.grid_offset)


def test_empty_space_is_only_in_front_of_the_surface(sphere_scan) -> None:  # type: ignore[no-untyped-def]
    config, scan = sphere_scan
    observation = scan.observations[5]
    band = band_keys(observation.keys, config.band_keys_sq)
    empty = sensor_empty(band, observation, config.camera, config.voxel_size, config.grid_offset)
    radii = np.linalg.norm(centres(config, band), axis=1)
    # Keys called empty lie outside the sphere: with `pixels` every one; with `targets` (one point per
    # visible voxel, so the depth buffer is splatted and thin at grazing rims) all but a few in 10^3.
    # Nearly all of the outside band facing the camera is found empty.
    assert empty.any()
    deep_inside = radii[empty] < RADIUS - config.voxel_size
    if config.imaging == "pixels":
        assert not deep_inside.any()
    else:
        assert deep_inside.sum() <= 1e-3 * (radii < RADIUS).sum()
    camera = observation.origins[0]
    facing = (centres(config, band) @ camera > 0) & (radii > RADIUS + 3 * config.voxel_size)
    assert empty[facing].mean() > 0.9


def test_carve_keeps_the_hidden_side_and_drops_seen_empty_keys(sphere_scan) -> None:  # type: ignore[no-untyped-def]
    config, scan = sphere_scan
    refiner = make_refiner(config)
    observation = scan.observations[0]
    refined = refiner.refine([RefineRequest(observation, 0, "0" * 16, 0)])[0]
    assert refined.size and np.intersect1d(refined, observation.keys).size == 0
    band = band_keys(observation.keys, config.band_keys_sq)
    assert np.isin(refined, band).all()
    radii = np.linalg.norm(centres(config, refined), axis=1)
    inside_band = band[np.linalg.norm(centres(config, band), axis=1) < RADIUS - config.voxel_size]
    # Occupied band keys (inside the sphere) are kept (see the grazing-rim caveat above).
    assert np.isin(inside_band, refined).mean() >= 0.999
    # Hidden surface keys of P_gt near the observation are recovered.
    hidden = np.intersect1d(np.setdiff1d(scan.ground_truth.keys, observation.keys), band)
    assert np.isin(hidden, refined).mean() > 0.8
    assert (radii < RADIUS + 0.011).all()


@pytest.mark.parametrize("radius_sq", [0, 1, 2, 8, 9, 25, 30])
@pytest.mark.parametrize("shape", ["cloud", "shell", "line"])
def test_band_keys_matches_brute_force(radius_sq: int, shape: str) -> None:
    from datagen.pipeline.keys import pack_keys
    from datagen.pipeline.refine.base import band_offsets

    rng = np.random.default_rng(radius_sq)
    if shape == "cloud":
        keys = rng.integers(-20, 20, size=(40, 3))
    elif shape == "shell":
        keys = rng.integers(-25, 25, size=(30000, 3))
        keys = keys[np.abs(np.linalg.norm(keys, axis=1) - 20) < 0.8]
    else:
        keys = np.stack([np.arange(-30, 30), np.zeros(60, int), np.full(60, 7)], axis=1)
    keys = np.unique(keys, axis=0)
    packed = pack_keys(keys)
    brute = np.unique(pack_keys((keys[:, None, :] + band_offsets(radius_sq)[None]).reshape(-1, 3)))
    assert np.array_equal(band_keys(packed, radius_sq), brute)
    assert np.array_equal(band_keys(packed[:1], radius_sq), np.sort(pack_keys(keys[:1] + band_offsets(radius_sq))))
