"""Refiners: one `RefinerKind` per refiner, registered once (docs/pipeline.md section 4).

A refiner predicts R(O), the band keys an observation misses. Every layer asks its kind instead of
testing its name: the config validates ``refiner`` against `REFINERS`, hashes the files the kind
loads by content and leaves out of the hash the later fields it does not read; a worker builds it
with the kind's builder; the dataset card states the fields it reads; the engine asks whether one
host per node may run its network.

The builder and the hosting are named as ``"module:attribute"`` and imported when first used, so
this module (and the reader's install) never imports the generator, torch or Open3D. A package adds a
refiner with no file of ours touched: an entry point of the group ``datagen.refiners`` naming its
`RefinerKind`; a Ray worker finds it as the driver does.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from schemas.errors import DatagenError
from schemas.registry import Registry, load_named


class UnknownRefiner(DatagenError, ValueError):
    """A refiner no `RefinerKind` is registered for, or one whose code cannot be loaded."""


@dataclass(frozen=True)
class RefinerKind:
    """What one refiner is, for every layer that meets it."""

    name: str
    build: str | Callable[..., Any]
    """``(config, device, network) -> Refiner`` (`datagen.pipeline.refine.base.Refiner`), or where to
    import it; ``device`` and ``network`` (a node's shared host) matter only to a learned refiner."""
    summary: str = ""
    """One phrase for help texts."""
    fields: tuple[str, ...] = ()
    """The `GenerationConfig` fields it reads besides the band (what a dataset card states of it)."""
    files: tuple[str, ...] = ()
    """Config fields naming a file it loads: while it refines, each enters the config hash by the
    sha256 of the file's content (`GenerationConfig.canonical_dict`)."""
    hosting: str | Callable[..., Any] | None = None
    """A `datagen.pipeline.refine.factory.NetworkHosting` (or where to import it) when one host per
    node may run its network for every task there (`RunSettings.shared_refiner`); None: never."""

    def load_build(self) -> Callable[..., Any]:
        found: Callable[..., Any] = load_named(self.build, f"the {self.name!r} refiner's builder", UnknownRefiner)
        return found

    def load_hosting(self) -> Any:
        """The kind's `NetworkHosting`, or None when its network is never hosted."""
        if self.hosting is None:
            return None
        return load_named(self.hosting, f"the {self.name!r} refiner's hosting", UnknownRefiner)


REFINERS: Registry[RefinerKind] = Registry(
    "refiner", "datagen.refiners", error=UnknownRefiner, check=lambda entry: isinstance(entry, RefinerKind)
)
"""Every refiner by name, in registration order (``--refiner`` lists them in this order)."""


def register_refiner(kind: RefinerKind) -> RefinerKind:
    """Register ``kind`` under its name (once)."""
    return REFINERS.register(kind.name, kind)


def refiner_kind(name: str) -> RefinerKind:
    """The registered refiner ``name``; `UnknownRefiner` naming the known ones otherwise."""
    return REFINERS[name]


_FACTORY = "datagen.pipeline.refine.factory"

register_refiner(RefinerKind("none", f"{_FACTORY}:build_none", "no refinement: P(O) = O"))
register_refiner(RefinerKind("carve", f"{_FACTORY}:build_carve", "the band's keys no view's free space carves away"))
register_refiner(
    RefinerKind(
        "poisson",
        f"{_FACTORY}:build_poisson",
        "a screened Poisson surface of the observed cloud (Open3D)",
        fields=("poisson_depth",),
    )
)
register_refiner(
    RefinerKind(
        "poco",
        f"{_FACTORY}:build_poco",
        "POCO's learned occupancy with the shipped or given weights (torch)",
        fields=("poco_version", "poco_preset", "poco_threshold", "finetune_steps"),
        files=("poco_weights",),
        hosting=f"{_FACTORY}:POCO_HOSTING",
    )
)
