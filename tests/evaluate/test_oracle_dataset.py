"""One code path: what `datagen evaluate` asks a planner, and what its oracle answers, are exactly the
input and label the engine stored for the same object, rotation, initial view and config."""

from __future__ import annotations

import numpy as np
import pytest
from support.shards import EngineDataset, engine_dataset  # noqa: F401 (the fixture)

import storage
from datagen.config_io import load_config
from datagen.errors import ObjectError
from datagen.evaluate.oracle import OraclePlanner
from datagen.evaluate.scene import build_scene
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.setcover import views_to_mask
from datagen.pipeline.viewspace import build_view_space


def sorted_rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


@pytest.mark.slow
def test_oracle_and_input_reproduce_every_stored_single_view_sample(
    engine_dataset: EngineDataset,  # noqa: F811 (the fixture imported above)
) -> None:
    config = load_config(engine_dataset.config_file)
    dataset = storage.open_dataset(engine_dataset.url)
    columns = dataset.index.select(["object_id", "rotation", "view_state", "case_size"]).to_pydict()
    singles = {
        (obj, rot, state): row
        for row, (obj, rot, state, size) in enumerate(zip(*columns.values(), strict=True))
        if size == 1
    }
    listing = read_objects_file(engine_dataset.objects_file)
    view_space = build_view_space(config.view_space)
    refiner = make_refiner(config)
    checked = 0
    for spec in listing.objects:
        try:
            prepared = prepare_object(spec, config)
        except ObjectError:
            continue  # the fixture's corrupt mesh: its tasks failed in the engine too
        for rotation in range(config.rotations):
            refined = RefinedScene(build_scene(prepared, rotation, config, view_space), refiner, config)
            for view in range(config.num_views):
                row = singles[(spec.object_id, rotation, 1 << view)]
                situation = Situation(refined, view)
                plan = OraclePlanner().plan(situation)
                _, stored_label = dataset.masks(row)
                assert views_to_mask(plan.views) == stored_label, (spec.name, rotation, view)
                request = situation.request()
                stored = dataset[row]
                assert np.array_equal(request.view_state.astype(bool), stored["view_state"])
                np.testing.assert_allclose(sorted_rows(request.points), sorted_rows(stored["points"]), atol=1e-6)
                np.testing.assert_allclose(sorted_rows(request.observed), sorted_rows(stored["observed"]), atol=1e-6)
                checked += 1
    assert checked == 3 * config.rotations * config.num_views


def test_oracle_and_input_match_run_task_with_a_refiner_that_adds_keys(tmp_path) -> None:
    """Same check in memory with ``carve``, whose refinement adds keys, so the input is not just what was seen."""
    from datagen.pipeline.task import run_task
    from schemas.config import GenerationConfig

    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    config = GenerationConfig(refiner="carve", rotations=2)
    spec = read_objects_file(objects).objects[0]
    prepared = prepare_object(spec, config)
    view_space = build_view_space(config.view_space)
    refiner = make_refiner(config)
    result = run_task(prepared, 1, config, view_space, refiner)
    refined = RefinedScene(build_scene(prepared, 1, config, view_space), refiner, config)
    singles = [s for s in result.samples if s.case.bit_count() == 1]
    assert len(singles) == config.num_views
    added = 0
    for sample in singles:
        situation = Situation(refined, sample.case.bit_length() - 1)
        assert views_to_mask(OraclePlanner().plan(situation).views) == sample.label
        np.testing.assert_array_equal(situation.request().points, sample.point_centres(config))
        added += sample.points.size - sample.observed.size
    assert added > 0


def test_relabelled_scene_labels_like_a_fresh_one_without_refining_again(tmp_path) -> None:
    from schemas.config import GenerationConfig

    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:cone\n")
    config = GenerationConfig(refiner="carve")
    prepared = prepare_object(read_objects_file(objects).objects[0], config)
    scene = build_scene(prepared, 0, config, build_view_space(config.view_space))
    calls = []
    carve = make_refiner(config)

    class Counting:
        name, weights_id = carve.name, carve.weights_id

        def refine(self, requests):
            calls.append(len(requests))
            return carve.refine(requests)

    refined = RefinedScene(scene, Counting(), config)
    other = config.model_copy(update={"alpha": 24})
    relabelled = refined.relabelled(other)
    fresh = RefinedScene(scene, carve, other)
    labels = [relabelled.label(v).label for v in range(config.num_views)]
    assert labels == [fresh.label(v).label for v in range(config.num_views)]
    assert labels != [refined.label(v).label for v in range(config.num_views)]
    assert calls == [config.num_views]  # one batch of single views, shared by both alphas
