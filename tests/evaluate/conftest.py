"""Fixtures the evaluator's tests share: the default config without refinement and one quick object."""

from __future__ import annotations

from pathlib import Path

import pytest

from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.spec import ObjectSpec
from schemas.config import GenerationConfig


@pytest.fixture(scope="module")
def config() -> GenerationConfig:
    return GenerationConfig(refiner="none")


@pytest.fixture(scope="module")
def spec(tmp_path_factory: pytest.TempPathFactory) -> ObjectSpec:
    objects = Path(tmp_path_factory.mktemp("objects")) / "objects.txt"
    objects.write_text("builtin:capsule\n")
    return read_objects_file(objects).objects[0]
