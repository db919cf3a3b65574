"""The poisson refiner against an analytic sphere and a box: what it keeps is inside, and it fills
the hidden side that one view cannot see."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import trimesh

from datagen.errors import ConfigError
from datagen.pipeline.ground_truth import sample_ground_truth
from datagen.pipeline.imaging import Observation, image_task
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.refine import RefineRequest, band_keys, make_refiner
from datagen.pipeline.refine.freespace import sensor_empty
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

pytest.importorskip("open3d")

RADIUS = 0.05


def scan_of(mesh: trimesh.Trimesh, config: GenerationConfig):  # type: ignore[no-untyped-def]
    gt = sample_ground_truth(
        mesh.vertices, mesh.faces, config.voxel_size, config.grid_offset, 64.0, np.random.default_rng(0)
    )
    return image_task(mesh.vertices, mesh.faces, gt, build_view_space(config.view_space), config)


@pytest.fixture(scope="module")
def sphere_scan():  # type: ignore[no-untyped-def]
    config = GenerationConfig(refiner="poisson")
    return config, scan_of(trimesh.creation.icosphere(subdivisions=5, radius=RADIUS), config)


def centres(config: GenerationConfig, keys: np.ndarray) -> np.ndarray:
    return key_centres(unpack_keys(keys), config.voxel_size, config.grid_offset)


def refine(config: GenerationConfig, observation: Observation) -> np.ndarray:
    return make_refiner(config).refine([RefineRequest(observation, 0, "0" * 16, 0)])[0]


@pytest.mark.parametrize("view", [0, 11, 27])
def test_poisson_fills_the_hidden_sphere_band_and_keeps_to_the_inside(sphere_scan, view: int) -> None:  # type: ignore[no-untyped-def]
    config, scan = sphere_scan
    observation = scan.observations[view]
    refined = refine(config, observation)
    band = band_keys(observation.keys, config.band_keys_sq)
    unknown = np.setdiff1d(band, observation.keys)
    # R(O) lies in the unknown band and holds no key the sensor saw empty.
    assert refined.size and np.isin(refined, unknown).all()
    assert not sensor_empty(refined, observation, config.camera, config.voxel_size, config.grid_offset).any()
    radii = np.linalg.norm(centres(config, refined), axis=1)
    truth = unknown[np.linalg.norm(centres(config, unknown), axis=1) < RADIUS]
    # Precision: a smooth closed surface through half a sphere keeps (nearly) to the sphere; allow
    # a voxel of membrane error at the rim.
    assert (radii < RADIUS + config.voxel_size).mean() > 0.97
    # Recall of the true inside band keys, the hidden half included.
    assert np.isin(truth, refined).mean() > 0.9
    hidden = np.intersect1d(np.setdiff1d(scan.ground_truth.keys, observation.keys), band)
    assert np.isin(hidden, refined).mean() > 0.3


@pytest.fixture(scope="module")
def box_scan():  # type: ignore[no-untyped-def]
    box = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    return box, scan_of(box, GenerationConfig(refiner="poisson"))


@pytest.mark.parametrize("view", [0, 9, 20])
def test_poisson_is_more_precise_than_carving_on_a_box(box_scan, view: int) -> None:  # type: ignore[no-untyped-def]
    # Views that see two or three faces: Poisson closes the box with a rounded membrane, carving keeps
    # the whole hidden band. (A view of one face alone gives a plane, which Poisson cannot close well.)
    config = GenerationConfig(refiner="poisson")
    box, scan = box_scan
    observation = scan.observations[view]
    band = band_keys(observation.keys, config.band_keys_sq)
    unknown = np.setdiff1d(band, observation.keys)
    inside = box.contains(centres(config, unknown))
    truth = set(unknown[inside].tolist())

    def precision(keys: np.ndarray) -> float:
        return float(np.mean([key in truth for key in keys.tolist()]))

    poisson = refine(config, observation)
    carve = refine(config.model_copy(update={"refiner": "carve"}), observation)
    assert precision(poisson) > precision(carve) + 0.03
    assert precision(poisson) > 0.8
    assert np.isin(unknown[inside], poisson).mean() > 0.9


def test_poisson_is_deterministic(sphere_scan) -> None:  # type: ignore[no-untyped-def]
    config, scan = sphere_scan
    observation = Observation.combine([scan.observations[2], scan.observations[17]])
    first = refine(config, observation)
    assert np.array_equal(first, refine(config, observation))
    assert np.array_equal(first, np.unique(first))


def test_too_few_points_refine_to_nothing(sphere_scan) -> None:  # type: ignore[no-untyped-def]
    config, scan = sphere_scan
    observation = scan.observations[0]
    few = Observation(
        views=observation.views,
        origins=observation.origins,
        points=observation.points[:5],
        point_views=observation.point_views[:5],
        pixels=observation.pixels[:5],
        keys=np.unique(observation.keys[:5]),
    )
    assert refine(config, few).size == 0


def test_missing_open3d_is_one_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)
    monkeypatch.delitem(sys.modules, "datagen.pipeline.refine.poisson", raising=False)
    with pytest.raises(ConfigError, match=r"pip install 'datagen\[poisson\]'"):
        make_refiner(GenerationConfig(refiner="poisson"))
