"""Fixtures the evaluator's tests share: the default config without refinement, one quick object and its
scene at rotation 0."""

from __future__ import annotations

from pathlib import Path

import pytest

from datagen.evaluate.scene import build_scene
from datagen.evaluate.situation import RefinedScene
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig


@pytest.fixture(scope="module")
def config() -> GenerationConfig:
    return GenerationConfig(refiner="none")


@pytest.fixture(scope="module")
def spec(tmp_path_factory: pytest.TempPathFactory) -> ObjectSpec:
    objects = Path(tmp_path_factory.mktemp("objects")) / "objects.txt"
    objects.write_text("builtin:capsule\n")
    return read_objects_file(objects).objects[0]


@pytest.fixture(scope="module")
def real(spec: ObjectSpec, config: GenerationConfig) -> RefinedScene:
    """The capsule at rotation 0, imaged from the default 32 views, refiner none."""
    scene = build_scene(prepare_object(spec, config), 0, config, build_view_space(config.view_space))
    return RefinedScene(scene, make_refiner(config), config)
