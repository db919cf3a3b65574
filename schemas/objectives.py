"""Label objectives: one `Objective` per objective, registered once (docs/pipeline.md sections 7, 7.5).

An objective says what the label of a case is. Every layer asks its objective instead of testing its
name: the config validates and hashes the label fields it reads (`Objective.fields`); generation,
`relabel` and `datagen evaluate`'s oracle build its labeller (generator side,
`datagen.pipeline.objectives`); `storage.validate` and the readers judge a stored label and its ties
with its judge (storage side, numpy only, `storage.label_judges`); evaluate takes its oracle settings.

The labeller and the judge are named as ``"module:attribute"`` and imported when first used, so this
module (and the reader's install) imports neither the generator nor storage; a test or plug-in may
pass the objects themselves. Adding an objective is its labeller, its judge and one
`register_objective` call with their tests: nothing else branches on objective names.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from schemas.errors import DatagenError
from schemas.registry import Registry, load_named

JudgedOn = Literal["refined", "visible"]


class UnknownObjective(DatagenError, ValueError):
    """A label objective no `Objective` is registered for."""


@dataclass(frozen=True)
class Objective:
    """What one label objective is, for every layer that meets it."""

    name: str
    judged_on: JudgedOn
    """The task sets its labels are judged on: the refined views' coverage of P_full ("refined": the
    labels need refinement) or what each view sees ("visible": they do not)."""
    fields: tuple[str, ...] = ()
    """The `GenerationConfig` label fields it reads besides ``alpha``; the others never enter the
    config hash of its datasets (they change nothing)."""
    ranks_ties: bool = False
    """Whether ``label_tie_break`` may rank its tied labels (by the cover problem's U); else ties go
    to the lowest view indices and ``label_tie_break`` must stay "index"."""
    oracle_settings: Mapping[str, str] = field(default_factory=dict)
    """``oracle:NAME=V`` of `datagen evaluate`: the setting names that imply this objective, each to
    the config field it sets."""
    labeller: str | Callable[..., Any] = ""
    """The generator side: a `datagen.pipeline.objectives.LabellerFactory`, or where to import it."""
    judge: str | Callable[..., Any] = ""
    """The storage side: a `storage.label_judges.LabelJudge` factory, or where to import it."""
    checker: str | Callable[..., Any] = ""
    """``shards validate --all``: a `datagen.inspection.label_check.LabelChecker` factory that finds
    the best label by other means than the labeller (brute force, HiGHS), or where to import it."""
    ties_words: tuple[str, str] = ("ties", "no tie")
    """What its listed equally good sets are called, and a label without any (`shards stats`)."""
    text_names: Mapping[str, str] = field(default_factory=dict)
    """How `GenerationConfig.objective_text` names each of its fields (e.g. label_budget -> budget)."""

    @property
    def needs_refinement(self) -> bool:
        return self.judged_on == "refined"

    def load_labeller(self) -> Callable[..., Any]:
        return _resolve(self.labeller, f"the {self.name!r} objective's labeller")

    def load_judge(self) -> Callable[..., Any]:
        return _resolve(self.judge, f"the {self.name!r} objective's judge")

    def load_checker(self) -> Callable[..., Any]:
        return _resolve(self.checker, f"the {self.name!r} objective's full check")


def _resolve(target: str | Callable[..., Any], what: str) -> Callable[..., Any]:
    found: Callable[..., Any] = load_named(target, what, UnknownObjective)
    return found


OBJECTIVES: Registry[Objective] = Registry(
    "label objective",
    "datagen.objectives",
    error=UnknownObjective,
    check=lambda entry: isinstance(entry, Objective),
)
"""Every label objective by name, in registration order; a package adds one as an entry point of
the group ``datagen.objectives`` naming its `Objective`."""


def register_objective(objective: Objective) -> Objective:
    """Register ``objective`` under its name (once)."""
    return OBJECTIVES.register(objective.name, objective)


def objective_named(name: str) -> Objective:
    """The registered objective ``name``; `UnknownObjective` naming the known ones otherwise."""
    return OBJECTIVES[name]


def label_fields() -> frozenset[str]:
    """Every label field some objective reads."""
    return frozenset(name for objective in OBJECTIVES.values() for name in objective.fields)


register_objective(
    Objective(
        name="cover",
        judged_on="refined",
        ranks_ties=True,
        oracle_settings={"alpha": "alpha"},
        labeller="datagen.pipeline.objectives:cover_labeller",
        judge="storage.samples:CoverJudge",
        checker="datagen.inspection.cover_check:cover_checker",
        ties_words=("minimum covers", "unique minimum cover"),
    )
)
register_objective(
    Objective(
        name="max_coverage",
        judged_on="visible",
        fields=("label_budget",),
        oracle_settings={"budget": "label_budget"},
        labeller="datagen.pipeline.objectives:max_coverage_labeller",
        judge="storage.samples:BudgetJudge",
        checker="datagen.inspection.coverage_check:budget_checker",
        text_names={"label_budget": "budget"},
    )
)
register_objective(
    Objective(
        name="partial_cover",
        judged_on="visible",
        fields=("label_tau",),
        oracle_settings={"tau": "label_tau"},
        labeller="datagen.pipeline.objectives:partial_cover_labeller",
        judge="storage.samples:TauJudge",
        checker="datagen.inspection.coverage_check:tau_checker",
        text_names={"label_tau": "tau"},
    )
)
