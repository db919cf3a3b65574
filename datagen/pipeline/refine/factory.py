"""Build the refiner a config names: the builders and the network hosting the built-in refiners'
`schemas.refiners.RefinerKind` entries name.

The ``poisson`` and ``poco`` builders import their modules (Open3D, torch) only when called, so a
worker that never uses them never loads them; a missing optional dependency is a `ConfigError` that
says what to install. `make_refiner` asks the registry, so a plug-in refiner (an entry point of
``datagen.refiners``) is built here like a built-in one.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from datagen.errors import ConfigError
from datagen.pipeline.refine.base import Refiner
from datagen.pipeline.refine.carve import CarveRefiner
from datagen.pipeline.refine.none import NoRefiner
from schemas.config import GenerationConfig
from schemas.refiners import UnknownRefiner

if TYPE_CHECKING:
    from datagen.pipeline.refine.poco.network_jobs import NetworkRunner
    from datagen.pipeline.refine.poco.refiner import PocoRefiner

RefinerBuilder = Callable[[GenerationConfig, str, "NetworkRunner | None"], Refiner]
"""(config, device, network) -> the refiner; ``device`` and ``network`` (who runs a network's jobs:
a node's shared host) only matter to a learned refiner."""


def poco_weights_path(config: GenerationConfig) -> Path:
    """The weights file the config names: for "builtin" the shipped file, the one whose content
    enters the config hash (`schemas.config.builtin_poco_weights`)."""
    return config.poco_weights_path()


@functools.lru_cache(maxsize=4)
def _load_poco(path: str, preset: str | None, mtime_ns: int, device: str) -> tuple[Any, str]:
    """The model and the sha256 of its file, once per worker process (per file version, preset, device).

    Ray keeps worker processes alive between tasks, so a worker loads the weights once and every
    later task on it reuses them. Preset None: the one saved with the weights (`load_checkpoint`).
    """
    from datagen.pipeline.refine.poco.checkpoint import load_checkpoint
    from datagen.pipeline.refine.poco.refiner import weights_sha256

    try:
        model = load_checkpoint(path, preset).to(device)
    except (RuntimeError, ValueError) as error:
        as_what = "with their saved preset" if preset is None else f"as preset {preset!r}"
        raise ConfigError(f"{path}: cannot load POCO weights {as_what} ({error})") from None
    return model, weights_sha256(Path(path))


def build_none(config: GenerationConfig, device: str, network: NetworkRunner | None = None) -> Refiner:
    return NoRefiner()


def build_carve(config: GenerationConfig, device: str, network: NetworkRunner | None = None) -> Refiner:
    return CarveRefiner(config)


def build_poisson(config: GenerationConfig, device: str, network: NetworkRunner | None = None) -> Refiner:
    try:
        from datagen.pipeline.refine.poisson import PoissonRefiner
    except ImportError as error:
        raise ConfigError(
            f"refiner = 'poisson' needs Open3D ({error}); install it with: pip install 'datagen[poisson]'"
        ) from None
    return PoissonRefiner(config)


def build_poco(config: GenerationConfig, device: str, network: NetworkRunner | None = None) -> Refiner:
    """With ``network`` (a shared host runs the network) the task keeps a CPU copy for its preset."""
    return load_poco_refiner(config, "cpu" if network is not None else device, config.poco_preset, network)


def load_poco_refiner(
    config: GenerationConfig, device: str = "cpu", preset: str | None = None, network: NetworkRunner | None = None
) -> PocoRefiner:
    """The ``poco`` refiner of the config's weights (`poco_weights_path`), threshold and fine-tuning.

    A worker's preset is the config's (`build_poco`); ``datagen poco eval`` passes None, the preset
    saved with the weights, unless its ``--preset`` names one.
    """
    try:
        from datagen.pipeline.refine.poco.refiner import PocoRefiner
    except ImportError as error:
        raise ConfigError(
            f"refiner = 'poco' needs torch ({error}); install it (pip install torch; the CPU build is enough)"
        ) from None
    path = poco_weights_path(config)
    if not path.is_file():
        raise ConfigError(f"{path}: POCO weights file not found; set poco_weights to a weights file or 'builtin'")
    model, sha = _load_poco(str(path.resolve()), preset, path.stat().st_mtime_ns, device)
    return PocoRefiner(config, model, sha, config.poco_threshold, config.finetune_steps, device=device, network=network)


@dataclass(frozen=True)
class NetworkHosting:
    """How a refiner with a network lets one host per node run it for every task there
    (`RunSettings.shared_refiner`, `datagen.engine.refiner_host`)."""

    shares: Callable[[GenerationConfig], bool]
    """Whether a config's refinement can go to a shared host at all."""
    host: Callable[[GenerationConfig, str, int], Any]
    """(config, device, jobs per encoder call) -> the `network_jobs.NetworkHost` that runs it."""


def _poco_host(config: GenerationConfig, device: str, encoder_batch: int) -> Any:
    from datagen.pipeline.refine.poco.network_jobs import NetworkHost

    refiner = load_poco_refiner(config, device, config.poco_preset)
    return NetworkHost(refiner.model, refiner.weights_id, device, refiner.knn_backend, encoder_batch=encoder_batch)


POCO_HOSTING = NetworkHosting(lambda config: config.finetune_steps == 0, _poco_host)
"""The ``poco`` refiner's network on a shared host; a fine-tuned network is each observation's own."""


def make_refiner(config: GenerationConfig, device: str = "cpu", network: NetworkRunner | None = None) -> Refiner:
    """The config's refiner; ``device`` ('cpu' or 'cuda') places a learned one (RunSettings.refiner_gpus),
    ``network`` runs its network elsewhere (RunSettings.shared_refiner)."""
    try:
        build: RefinerBuilder = config.refiner_kind.load_build()
    except UnknownRefiner as error:
        raise ConfigError(str(error)) from None
    return build(config, device, network)


def network_hosting(config: GenerationConfig) -> NetworkHosting | None:
    """How one host per node may run the config's refiner network, or None (`RefinerKind.hosting`)."""
    hosting = config.refiner_kind.load_hosting()
    return hosting if isinstance(hosting, NetworkHosting) else None
