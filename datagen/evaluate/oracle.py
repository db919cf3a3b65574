"""The ``oracle`` planner: the generator's exact label for the very case, under the evaluation's label
settings or ``oracle:SETTING=V[,...]`` changes to them (each registered objective's oracle settings,
`schemas.objectives.Objective.oracle_settings`), so one evaluation compares label objectives.
"""

from __future__ import annotations

from collections.abc import Iterable

from pydantic import ValidationError

from datagen.errors import PlannerError
from datagen.evaluate.protocol import Plan
from datagen.evaluate.situation import Situation, needs_refinement
from datagen.pipeline.setcover import mask_to_views
from schemas.config import GenerationConfig
from schemas.objectives import OBJECTIVES, UnknownObjective, objective_named


def oracle_setting_fields() -> dict[str, str]:
    """``oracle:SETTING=V``: the config field each setting name changes (``objective``, and each
    registered objective's `Objective.oracle_settings`)."""
    fields = {"objective": "label_objective"}
    for objective in OBJECTIVES.values():
        fields.update(objective.oracle_settings)
    return fields


def implied_objectives(names: Iterable[str]) -> set[str]:
    """The objectives the settings imply when ``objective`` is not named."""
    owners = {setting: objective.name for objective in OBJECTIVES.values() for setting in objective.oracle_settings}
    return {owners[name] for name in names if name in owners}


def _setting_type(field: str) -> type:
    """int, float or str: the type of the config field a setting changes."""
    annotation = GenerationConfig.model_fields[field].annotation
    return int if annotation is int else float if annotation is float else str


class OraclePlanner:
    """The generator's label for the case, under the evaluation's label settings or ``changes`` to them."""

    def __init__(
        self, config: GenerationConfig | None = None, changes: dict[str, object] | None = None, name: str = ""
    ) -> None:
        self.changes = dict(changes or {})
        self.config = oracle_config(config or GenerationConfig(), self.changes)
        self.name = name or "oracle" + (
            ":" + ",".join(f"{k}={v}" for k, v in self.changes.items()) if self.changes else ""
        )
        self.uses_refinement = needs_refinement(self.config)
        self._configs: dict[int, GenerationConfig] = {}

    def plan(self, situation: Situation) -> Plan:
        config = situation.config
        if self.changes:  # the scene's config may be another than the one the planner was built with
            if id(config) not in self._configs:
                self._configs[id(config)] = oracle_config(config, self.changes)
            config = self._configs[id(config)]
        return Plan(views=mask_to_views(situation.oracle_label(config).label))


def oracle_settings(spec: str, argument: str) -> dict[str, object]:
    """``alpha=5`` or ``budget=2`` or ``objective=partial_cover,tau=0.95`` as setting -> value."""
    changes: dict[str, object] = {}
    for part in argument.split(","):
        name, equals, value = part.strip().partition("=")
        fields = oracle_setting_fields()
        if not equals or name not in fields or not value:
            choices = ", ".join(f"{n}=V" for n in fields)
            raise PlannerError(f"planner {spec!r}: give label settings as {choices}, separated by commas")
        try:
            changes[name] = _setting_type(fields[name])(value)
        except ValueError:
            kind = "whole number" if _setting_type(fields[name]) is int else "number"
            raise PlannerError(f"planner {spec!r}: {name}={value} is not a {kind}") from None
    return changes


def oracle_config(config: GenerationConfig, changes: dict[str, object]) -> GenerationConfig:
    """``config`` with the oracle's label setting changes (a setting implies its objective)."""
    fields = oracle_setting_fields()
    update = {fields[name]: value for name, value in changes.items()}
    if "objective" not in changes:
        implied = implied_objectives(changes)
        if len(implied) == 1:
            update["label_objective"] = implied.pop()
    try:
        if not objective_named(str(update.get("label_objective", config.label_objective))).ranks_ties:
            update["label_tie_break"] = "index"
        return GenerationConfig.model_validate({**config.model_dump(), **update})
    except UnknownObjective as exc:
        raise PlannerError(f"oracle setting objective: {exc}") from None
    except ValidationError as exc:
        first = exc.errors()[0]
        setting = next((n for n, f in fields.items() if first["loc"] and f == first["loc"][0]), "oracle")
        raise PlannerError(f"oracle setting {setting}: {first['msg']}") from None
