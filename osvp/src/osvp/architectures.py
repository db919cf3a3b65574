"""The planner networks ``osvp train --network`` can build, in one registry.

Every architecture maps the same two inputs of the sample contract to one logit per candidate view:
what it reads of the case (``reads``: the cloud ``points``, or the occupancy ``grid``) and the view
state. The training loop, checkpoints, metrics and planners only ask the registry, so a new family
is one `register_architecture` call:

- ``osvp``: AIR-OSVP's point-cloud and view-state transformers (`osvp.network`); with the ``gain``
  target it is a PCNBV-style next-best-view planner (cloud and view state in, every view's gain out).
- ``nbvnet``: NBVNet's 3D CNN on the grid (`osvp.grid_network`), the best next view as a class.
- ``scvp``: the same CNN with the view state joined, a one-shot set-cover planner in SCVP's manner.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, Protocol

from torch import nn

from osvp.grid_network import NBVNET_PRESETS, SCVP_PRESETS, GridNetwork, GridPreset
from osvp.network import PRESETS, NetworkPreset, OSVPNetwork
from schemas.errors import DatagenError
from schemas.registry import Registry

Reads = Literal["points", "grid"]
DEFAULT_ARCHITECTURE = "osvp"
"""What a checkpoint written before architectures were recorded holds."""


class Preset(Protocol):
    """What every architecture's preset gives: its name, the points a batch carries, plain data."""

    @property
    def name(self) -> str: ...
    @property
    def num_points(self) -> int: ...
    def as_dict(self) -> dict[str, object]: ...


@dataclass(frozen=True)
class Architecture:
    """A network family: what it reads, its named presets, how a stored preset is parsed and how it is built."""

    name: str
    reads: Reads
    presets: Mapping[str, Preset]
    parse_preset: Callable[[dict[str, object]], Preset]
    build: Callable[[Preset, int], nn.Module]
    default_target: str
    """What ``osvp train`` trains it on unless told (`osvp.loss.TARGETS`): the best measured settings."""
    summary: str = ""
    """One phrase for ``osvp train --help`` (its ``--network`` choices are written from the registry)."""

    def preset(self, name: str) -> Preset:
        if name not in self.presets:
            raise ValueError(f"network {self.name!r} has no preset {name!r}; choose {', '.join(sorted(self.presets))}")
        return self.presets[name]


class UnknownNetwork(DatagenError, ValueError):
    """A network family no `Architecture` is registered for."""


ARCHITECTURES: Registry[Architecture] = Registry(
    "network", "osvp.networks", error=UnknownNetwork, check=lambda entry: isinstance(entry, Architecture)
)
"""The network families by name (`register_architecture`); a package adds one as an entry point of
the group ``osvp.networks`` naming its `Architecture`."""


def register_architecture(architecture: Architecture) -> Architecture:
    """Add a family to `ARCHITECTURES` (a name is registered once)."""
    return ARCHITECTURES.register(architecture.name, architecture)


def architecture(name: str) -> Architecture:
    """The registered architecture ``name``, or one `UnknownNetwork` line listing the choices."""
    return ARCHITECTURES[name]


def _build_osvp(preset: Preset, num_views: int) -> nn.Module:
    assert isinstance(preset, NetworkPreset)
    return OSVPNetwork(preset, num_views)


def _build_grid(preset: Preset, num_views: int) -> nn.Module:
    assert isinstance(preset, GridPreset)
    return GridNetwork(preset, num_views)


# The recipe measured ``mincover`` best for the one-shot planners (osvp/recipe/RESULTS.md, issue 21);
# NBVNet is a classifier of the best next view.
register_architecture(
    Architecture(
        "osvp",
        "points",
        PRESETS,
        NetworkPreset.from_dict,
        _build_osvp,
        "mincover",
        "AIR-OSVP's cloud and view-state transformers (with --target gain a PCNBV-style next-best-view planner)",
    )
)
register_architecture(
    Architecture(
        "nbvnet",
        "grid",
        NBVNET_PRESETS,
        GridPreset.from_dict,
        _build_grid,
        "best_view",
        "NBVNet's 3D CNN on the occupancy grid, the best next view as a class (a version-3 dataset)",
    )
)
register_architecture(
    Architecture(
        "scvp",
        "grid",
        SCVP_PRESETS,
        GridPreset.from_dict,
        _build_grid,
        "mincover",
        "the same CNN with the view state, a one-shot set-cover planner (a version-3 dataset)",
    )
)


def architecture_help() -> str:
    """Every registered network family and what it is, for ``--network``'s help."""
    return "; ".join(f"{name}: {family.summary}" for name, family in ARCHITECTURES.items())


def preset_names() -> tuple[str, ...]:
    """Every preset name some architecture has (each built-in has ``small`` and ``paper``), sorted."""
    return tuple(sorted({name for family in ARCHITECTURES.values() for name in family.presets}))
