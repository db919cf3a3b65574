"""Build the refiner a config names."""

from __future__ import annotations

from datagen.errors import ConfigError
from datagen.refine.base import Refiner
from datagen.refine.carve import CarveRefiner
from datagen.refine.none import NoRefiner
from schemas.config import GenerationConfig


def make_refiner(config: GenerationConfig) -> Refiner:
    if config.refiner == "none":
        return NoRefiner()
    if config.refiner == "carve":
        return CarveRefiner(config)
    raise ConfigError(f"refiner = {config.refiner!r} is not available; use refiner = 'none' or 'carve'")
