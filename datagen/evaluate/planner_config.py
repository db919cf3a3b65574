"""The generation config an evaluation images objects with, when trained planners say what they expect.

A trained planner has only seen its training data's scenes: clouds and grids made at one voxel size,
from one view space and camera. A checkpoint that records its data's config (`schemas.planning`:
a scorer's ``generation_config``) is played on objects imaged the same way:

- without ``--config``, the evaluation takes the planner's own config (its refiner too, unless
  ``--refiner`` names others): ``datagen evaluate -p shipped:nbv`` needs nothing else;
- with ``--config``, a config that images objects otherwise (`GenerationConfig.scene_identity`) is
  refused in one line naming the fields that differ, before any imaging;
- two planners that expect different scenes cannot share one evaluation (one line, again).

Planners that record nothing (built-ins, older checkpoints, other plug-ins) leave the config as given.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from datagen.errors import ConfigError, InvalidArgument
from datagen.evaluate.planners import PlannerSpec, lookup_planner
from datagen.evaluate.scored import plugin_scorer
from schemas.config import GenerationConfig
from schemas.planning import ViewScorer


@dataclass(frozen=True)
class EvaluationConfig:
    """The config to image with and the refiners to refine the planners' inputs with."""

    config: GenerationConfig
    refiners: tuple[str, ...]
    source: str
    """Where the config came from: ``--config``, a planner's name, or ``the defaults``."""


@dataclass(frozen=True)
class Expected:
    """What one planner expects: its training data's config, and whether it reads the refined cloud."""

    config: GenerationConfig
    refined: bool


def expected_configs(planners: Sequence[str]) -> dict[str, Expected]:
    """What each named plug-in planner that records its config expects, by its name as given."""
    found: dict[str, Expected] = {}
    for text in planners:
        spec = PlannerSpec.parse(text)
        kind = lookup_planner(spec.name, text)
        if kind.plugin is None or not spec.argument:
            continue
        scorer = plugin_scorer(kind.plugin, spec.argument, text)
        recorded = getattr(scorer, "generation_config", None)
        if recorded is None:
            continue
        try:
            config = GenerationConfig.model_validate(_portable(recorded))
        except ValueError as exc:
            first = str(exc).splitlines()[0]
            raise ConfigError(
                f"planner {text!r}: the generation config it records is not valid here ({first})"
            ) from None
        refined = isinstance(scorer, ViewScorer) and not getattr(scorer, "uses_grid", False)
        found[text] = Expected(config, refined and getattr(scorer, "source", "points") != "observed")
    return found


def _portable(recorded: dict[str, Any]) -> dict[str, Any]:
    """A recorded config as this machine can load it: files named by content on the training machine
    (a view-space file, POCO weights) cannot be read here, and only their sha256 entered the scene."""
    data = dict(recorded)
    for name in ("poco_weights",):
        value = data.get(name)
        if isinstance(value, str) and value.startswith("sha256:"):
            data.pop(name)
    return data


def resolve_evaluation_config(
    given: GenerationConfig | None,
    planners: Sequence[str],
    refiners: Sequence[str] | None,
) -> EvaluationConfig:
    """The config and refiners of an evaluation of ``planners`` (``given``: ``--config``'s, if any)."""
    expected = expected_configs(planners)
    if given is not None:
        for name, wanted in expected.items():
            differences = _differences(wanted.config, given)
            if differences:
                raise InvalidArgument(
                    f"planner {name!r} was trained on objects imaged with {_describe(differences, 0)}, but --config "
                    f"gives {_describe(differences, 1)}; leave --config out to image as the planner expects"
                )
        return EvaluationConfig(given, tuple(refiners or [given.refiner]), "--config")
    if not expected:
        default = GenerationConfig()
        return EvaluationConfig(default, tuple(refiners or [default.refiner]), "the defaults")
    (first_name, first), *others = ((name, wanted.config) for name, wanted in expected.items())
    for name, config in others:
        differences = _differences(first, config)
        if differences:
            raise InvalidArgument(
                f"planners {first_name!r} and {name!r} expect objects imaged otherwise ({_describe(differences, 0)} "
                f"against {_describe(differences, 1)}); evaluate them apart"
            )
    read = tuple(dict.fromkeys(wanted.config.refiner for wanted in expected.values() if wanted.refined))
    return EvaluationConfig(first, tuple(refiners or read or [first.refiner]), f"planner {first_name}")


def _differences(first: GenerationConfig, second: GenerationConfig) -> list[tuple[str, Any, Any]]:
    ours, theirs = first.scene_identity(), second.scene_identity()
    return [(name, ours[name], theirs[name]) for name in ours if ours[name] != theirs[name]]


def _describe(differences: list[tuple[str, Any, Any]], side: int) -> str:
    return ", ".join(f"{name} {values[side]}" for name, *values in differences)
