"""Planners that ship inside osvp: ``datagen evaluate --planner shipped:NAME`` with no training.

Each is a small checkpoint beside this module, trained by the committed commands of
``studies/planners/real_objects/`` on the real-object split, with its sha256 and a training card
(data, config, steps, scores) in `CARDS`. `load_shipped` is the `schemas.planning.ScorerFactory` osvp
registers as entry point ``shipped`` (pyproject.toml): it checks the file's hash before torch reads a
byte, so a missing, truncated or replaced checkpoint is one line naming the fix, never a planner that
plays with other weights than its card describes.

This module imports no torch (``datagen evaluate --help`` lists `NAMES` from it).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from schemas.errors import DatagenError
from schemas.registry import Registry

if TYPE_CHECKING:
    from osvp.planning import CheckpointScorer, NextViewCheckpointScorer

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class ShippedPlanner:
    """One shipped planner: its checkpoint file, the file's sha256, and what it is."""

    name: str
    file: str
    sha256: str
    summary: str
    folder: Path | None = None
    """Where the checkpoint and its card live: a plug-in's own package folder (None: osvp's, `HERE`)."""

    @property
    def path(self) -> Path:
        return (self.folder or HERE) / self.file

    @property
    def card(self) -> Path:
        """The training card beside the checkpoint: data, config, commands, steps and scores."""
        return (self.folder or HERE) / f"{self.name}.md"


class ShippedPlannerError(DatagenError):
    """A shipped planner is unknown, missing or not the file its hash names."""


SHIPPED: Registry[ShippedPlanner] = Registry(
    "shipped planner",
    "osvp.shipped_planners",
    error=ShippedPlannerError,
    check=lambda entry: isinstance(entry, ShippedPlanner),
)
"""The shipped planners by name (`register_shipped`); a package ships one more as an entry point of
the group ``osvp.shipped_planners`` naming its `ShippedPlanner` (its checkpoint in its own folder)."""


def register_shipped(planner: ShippedPlanner) -> ShippedPlanner:
    return SHIPPED.register(planner.name, planner)


register_shipped(
    ShippedPlanner(
        name="nbv",
        file="nbv.pt",
        sha256="fac57beea62d9975525fc62d82b071ca11d39f60dde0c5a8ff6d2db92aba8ad1",
        summary="the next-best-view planner, played step by step",
    )
)
register_shipped(
    ShippedPlanner(
        name="oneshot",
        file="oneshot.pt",
        sha256="f8675a27b053a88812729827261701c84e29be266631fb3b56134a1c6d958a5f",
        summary="the one-shot planner, its views taken at once",
    )
)


def verified_path(name: str) -> Path:
    """The checkpoint of shipped planner ``name`` once its bytes match its recorded sha256."""
    planner = SHIPPED.get(name)
    if planner is None:
        raise ShippedPlannerError(f"no shipped planner {name!r}; choose {', '.join(f'shipped:{n}' for n in SHIPPED)}")
    reinstall = "reinstall osvp (pip install --force-reinstall ./osvp)"
    if not planner.path.is_file():
        raise ShippedPlannerError(f"shipped:{name}: its checkpoint {planner.path} is missing; {reinstall}")
    with planner.path.open("rb") as handle:
        digest = hashlib.file_digest(handle, "sha256").hexdigest()
    if digest != planner.sha256:
        raise ShippedPlannerError(
            f"shipped:{name}: {planner.path} is damaged or replaced (sha256 {digest[:12]}, shipped "
            f"{planner.sha256[:12]}); {reinstall}"
        )
    return planner.path


class ShippedFactory:
    """The entry point ``shipped`` (a `schemas.planning.ScorerFactory`): ``shipped:NAME`` is the scorer of
    shipped planner NAME, its hash checked first. `choices` tells ``datagen evaluate --help`` the names."""

    @property
    def choices(self) -> tuple[str, ...]:
        return tuple(SHIPPED)

    def __call__(self, name: str, device: str = "cpu") -> CheckpointScorer | NextViewCheckpointScorer:
        from osvp.planning import load_scorer

        return load_scorer(verified_path(name), device)


load_shipped = ShippedFactory()
