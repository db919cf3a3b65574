"""Build the refiner a config names."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from datagen.errors import ConfigError
from datagen.pipeline.refine.base import Refiner
from datagen.pipeline.refine.carve import CarveRefiner
from datagen.pipeline.refine.none import NoRefiner
from schemas.config import BUILTIN_POCO_WEIGHTS, GenerationConfig


def poco_weights_path(config: GenerationConfig) -> Path:
    if config.poco_weights == BUILTIN_POCO_WEIGHTS:
        from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS

        return BUILTIN_WEIGHTS
    return Path(config.poco_weights)


@functools.lru_cache(maxsize=4)
def _load_poco(path: str, preset: str, mtime_ns: int, device: str) -> tuple[Any, str]:
    """The model and the sha256 of its file, once per worker process (per file version, preset, device).

    Ray keeps worker processes alive between tasks, so a worker loads the weights once and every
    later task on it reuses them.
    """
    from datagen.pipeline.refine.poco.checkpoint import load_checkpoint
    from datagen.pipeline.refine.poco.refiner import weights_sha256

    try:
        model = load_checkpoint(path, preset).to(device)
    except (RuntimeError, ValueError) as error:
        raise ConfigError(f"{path}: cannot load POCO weights as preset {preset!r} ({error})") from None
    return model, weights_sha256(Path(path))


def make_refiner(config: GenerationConfig, device: str = "cpu") -> Refiner:
    """The config's refiner; ``device`` ('cpu' or 'cuda') places a learned one (RunSettings.refiner_gpus)."""
    if config.refiner == "none":
        return NoRefiner()
    if config.refiner == "carve":
        return CarveRefiner(config)
    if config.refiner == "poisson":
        try:
            from datagen.pipeline.refine.poisson import PoissonRefiner
        except ImportError as error:
            raise ConfigError(
                f"refiner = 'poisson' needs Open3D ({error}); install it with: pip install 'datagen[poisson]'"
            ) from None
        return PoissonRefiner(config)
    if config.refiner == "poco":
        try:
            from datagen.pipeline.refine.poco.refiner import PocoRefiner
        except ImportError as error:
            raise ConfigError(
                f"refiner = 'poco' needs torch ({error}); install it (pip install torch; the CPU build is enough)"
            ) from None
        path = poco_weights_path(config)
        if not path.is_file():
            raise ConfigError(f"{path}: POCO weights file not found; set poco_weights to a weights file or 'builtin'")
        model, sha = _load_poco(str(path.resolve()), config.poco_preset, path.stat().st_mtime_ns, device)
        return PocoRefiner(config, model, sha, config.poco_threshold, config.finetune_steps, device=device)
    raise ConfigError(f"refiner = {config.refiner!r} is not available; use 'none', 'carve', 'poisson' or 'poco'")
