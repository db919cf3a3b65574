"""The refiner interface (docs/pipeline.md section 4, datagen/pipeline/refine): the band, P(O) = keys(O) united
with R(O), the ``none`` refiner, the factory (`make_refiner`), and the ``poco`` refiner running in a
process where training code cannot be imported."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from datagen.errors import ConfigError
from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import pack_keys, unpack_keys
from datagen.pipeline.refine import RefineRequest, band_keys, make_refiner, refined_keys
from datagen.pipeline.refine.base import band_offsets
from datagen.pipeline.refine.none import NoRefiner
from schemas.config import GenerationConfig


def observation(views: tuple[int, ...], packed: np.ndarray) -> Observation:
    """A minimal observation: one point per key, attributed to the first view."""
    count = packed.size
    return Observation(
        views=views,
        origins=np.zeros((len(views), 3)),
        points=np.zeros((count, 3), dtype=np.float32),
        point_views=np.full(count, views[0], dtype=np.uint8),
        pixels=np.zeros((count, 2), dtype=np.float32),
        keys=packed,
    )


def brute_ball(radius_sq: int) -> set[tuple[int, int, int]]:
    r = int(np.ceil(np.sqrt(radius_sq))) + 1
    axis = range(-r, r + 1)
    return {p for p in itertools.product(axis, axis, axis) if p[0] ** 2 + p[1] ** 2 + p[2] ** 2 <= radius_sq}


# ---------------------------------------------------------------------------------------------------------
# The band
# ---------------------------------------------------------------------------------------------------------


def test_default_band_is_radius_five_keys() -> None:
    assert GenerationConfig().band_keys_sq == 25


def test_band_offsets_radius_five() -> None:
    offsets = band_offsets(25)
    assert offsets.shape == (515, 3)  # integer points in a ball of radius 5
    assert ((offsets**2).sum(axis=1) <= 25).all()
    assert {tuple(o) for o in offsets.tolist()} == brute_ball(25)
    assert len({tuple(o) for o in offsets.tolist()}) == 515
    # Sorted (lexicographic x, y, z), as documented.
    order = np.lexsort((offsets[:, 2], offsets[:, 1], offsets[:, 0]))
    assert (order == np.arange(offsets.shape[0])).all()


@pytest.mark.parametrize(("radius_sq", "count"), [(0, 1), (1, 7), (2, 19), (3, 27), (4, 33), (5, 57), (9, 123)])
def test_band_offsets_small_counts(radius_sq: int, count: int) -> None:
    offsets = band_offsets(radius_sq)
    assert offsets.shape == (count, 3)
    assert {tuple(o) for o in offsets.tolist()} == brute_ball(radius_sq)


@pytest.mark.parametrize("key", [(0, 0, 0), (17, -40, 3), (-1000, 999, -5)])
def test_band_keys_of_one_key(key: tuple[int, int, int]) -> None:
    packed = pack_keys(np.array([key]))
    band = band_keys(packed, 25)
    expected = np.sort(pack_keys(np.array(key) + band_offsets(25)))
    assert band.dtype == np.int64
    assert np.array_equal(band, expected)
    assert np.isin(packed, band).all()  # the key itself is in its band
    assert ((unpack_keys(band) - np.array(key)) ** 2).sum(axis=1).max() == 25


def test_band_keys_of_several_keys_is_the_union() -> None:
    raw = np.array([[0, 0, 0], [3, 0, 0], [50, 50, 50]])
    packed = np.sort(pack_keys(raw))
    band = band_keys(packed, 25)
    union = np.unique(np.concatenate([band_keys(pack_keys(k[None, :]), 25) for k in raw]))
    assert np.array_equal(band, union)
    assert np.all(np.diff(band) > 0)  # sorted unique
    assert band.size == 2 * 515 - len(brute_ball(25) & {(x + 3, y, z) for x, y, z in brute_ball(25)}) + 515


def test_band_keys_of_nothing() -> None:
    assert band_keys(np.empty(0, dtype=np.int64), 25).size == 0


# ---------------------------------------------------------------------------------------------------------
# P(O) = keys(O) united with R(O)
# ---------------------------------------------------------------------------------------------------------


def test_refined_keys_is_the_union() -> None:
    o = observation((2,), np.array([5, 9, 20], dtype=np.int64))
    r = np.array([1, 9, 30], dtype=np.int64)
    assert refined_keys(o, r).tolist() == [1, 5, 9, 20, 30]
    assert refined_keys(o, np.empty(0, dtype=np.int64)).tolist() == [5, 9, 20]
    assert refined_keys(observation((0,), np.empty(0, dtype=np.int64)), r).tolist() == [1, 9, 30]


def test_refine_request_carries_the_case_mask() -> None:
    o = observation((1, 4, 5), np.array([7], dtype=np.int64))
    request = RefineRequest(o, seed=3, object_id="ab" * 32, rotation=2)
    assert request.mask == 0b110010


# ---------------------------------------------------------------------------------------------------------
# The ``none`` refiner and the factory
# ---------------------------------------------------------------------------------------------------------


def test_no_refiner_returns_one_empty_array_per_request() -> None:
    refiner = NoRefiner()
    assert refiner.name == "none"
    assert refiner.weights_id == ""
    requests = [
        RefineRequest(observation((v,), np.array([v, v + 10], dtype=np.int64)), 0, "0" * 64, 0) for v in range(5)
    ]
    out = refiner.refine(requests)
    assert len(out) == 5
    for r in out:
        assert isinstance(r, np.ndarray) and r.dtype == np.int64 and r.size == 0
    assert refiner.refine([]) == []
    # P(O) with the none refiner is what the sensor saw.
    for request, r in zip(requests, out, strict=True):
        assert np.array_equal(refined_keys(request.observation, r), request.observation.keys)


def test_make_refiner_none() -> None:
    refiner = make_refiner(GenerationConfig(refiner="none"))
    assert isinstance(refiner, NoRefiner)
    assert refiner.name == "none"
    assert refiner.weights_id == ""


def test_make_refiner_unknown_is_a_config_error() -> None:
    # The config schema refuses other names; bypass it to reach the factory's own check.
    config = GenerationConfig.model_construct(**{**GenerationConfig().__dict__, "refiner": "marching"})
    with pytest.raises(ConfigError, match="marching"):
        make_refiner(config)


def test_make_refiner_names_every_refiner() -> None:
    from schemas.refiners import REFINERS

    assert REFINERS.names() == ("none", "carve", "poisson", "poco")
    config = GenerationConfig.model_construct(**{**GenerationConfig().__dict__, "refiner": "marching"})
    with pytest.raises(ConfigError, match=r"unknown refiner 'marching'; choose one of none, carve, poisson, poco$"):
        make_refiner(config)


# ---------------------------------------------------------------------------------------------------------
# The ``poco`` refiner never loads training code
# ---------------------------------------------------------------------------------------------------------

REPO_ROOT = Path(__file__).resolve().parents[2]

BLOCKED_IN_WORKER = (
    "datagen.training",
    "datagen.engine",
    "datagen.cli",
    "datagen.inspection",
    "datagen.api",
    "trimesh",
)

REFINE_WITHOUT_TRAINING = textwrap.dedent(
    """
    import importlib.abc
    import json
    import sys

    BLOCKED = sys.argv[1].split(",")


    def blocked(name):
        return any(name == b or name.startswith(b + ".") for b in BLOCKED)


    class Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if blocked(name):
                raise ImportError(f"blocked import of {name}")
            return None


    sys.meta_path.insert(0, Blocker())
    assert not [name for name in sys.modules if blocked(name)]

    import numpy as np
    import torch

    torch.set_num_threads(1)
    for name in BLOCKED:  # the blocker really blocks
        try:
            __import__(name)
        except ImportError:
            pass
        else:
            raise SystemExit(f"{name} was importable despite the blocker")

    from datagen.pipeline.imaging import Observation
    from datagen.pipeline.refine import RefineRequest, make_refiner
    from schemas.config import GenerationConfig

    data = np.load(sys.argv[2])
    observation = Observation(
        views=tuple(int(v) for v in data["views"]),
        origins=data["origins"],
        points=data["points"],
        point_views=data["point_views"],
        pixels=data["pixels"],
        keys=data["keys"],
    )
    refiner = make_refiner(GenerationConfig(refiner="poco"))
    request = RefineRequest(observation, int(sys.argv[4]), sys.argv[5], int(sys.argv[6]))
    refined = refiner.refine([request])[0]
    np.save(sys.argv[3], refined)
    print(json.dumps({
        "refiner": type(refiner).__name__,
        "weights_id": refiner.weights_id,
        "loaded": sorted(name for name in sys.modules if blocked(name)),
    }))
    """
)


def test_poco_refines_in_a_process_that_cannot_import_training(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.objects.spec import BUILTIN_PREFIX, ObjectOptions, ObjectSpec, builtin_object_id
    from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS
    from datagen.pipeline.scanning import scan_task
    from datagen.pipeline.viewspace import build_view_space
    from datagen.shapes import builtins

    if not BUILTIN_WEIGHTS.is_file():
        pytest.skip("no shipped weights")
    # Preparing and scanning an object needs trimesh: done here, the observation goes over as a .npz.
    config = GenerationConfig(refiner="poco")
    options = ObjectOptions(size=0.08)
    identity = builtins.builtin_generator_identity("capsule")
    spec = ObjectSpec(
        source=BUILTIN_PREFIX + "capsule",
        name="capsule",
        options=options,
        object_id=builtin_object_id(identity, options),
        generator=identity,
    )
    imaging = scan_task(prepare_object(spec, config), 1, config, build_view_space(config.view_space))
    observation = imaging.observations[3]
    assert observation.keys.size > 0
    given = tmp_path / "observation.npz"
    np.savez(
        given,
        views=np.array(observation.views),
        origins=observation.origins,
        points=observation.points,
        point_views=observation.point_views,
        pixels=observation.pixels,
        keys=observation.keys,
    )
    out = tmp_path / "refined.npy"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO_ROOT))
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            REFINE_WITHOUT_TRAINING,
            ",".join(BLOCKED_IN_WORKER),
            str(given),
            str(out),
            "7",
            spec.object_id,
            "1",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["refiner"] == "PocoRefiner" and len(report["weights_id"]) == 64
    assert report["loaded"] == []  # datagen.training (and trimesh, the CLI, the engine) never came in
    refined = np.load(out)
    assert refined.dtype == np.int64 and refined.size > 0
    # The same keys as this process's refiner (one torch thread in both).
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        here = make_refiner(config).refine([RefineRequest(observation, 7, spec.object_id, 1)])[0]
    finally:
        torch.set_num_threads(before)
    np.testing.assert_array_equal(refined, here)
