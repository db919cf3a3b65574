"""Planners that never look at the object, and the matcher that gives them another planner's count.

- ``random`` / ``random:K``: seeded uniform views, as many as the oracle's (or K in all);
- ``fixed`` / ``fixed:K``: the best constant view set of that size, chosen once from a training
  dataset (``--fixed-from``, `datagen.evaluate.fixed`): the floor a planner that looks at the object
  must beat;
- ``spread`` / ``spread:K``: views spread far apart from the initial one, needing no data;
- ``KIND:match=SPEC``: that baseline with as many views as planner SPEC of the same run chose in the
  same situation (`match_planners`);
- ``all``: every candidate view.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from datagen.errors import PlannerError
from datagen.evaluate.fixed import FIXED_OPTION, FixedPlans, spread_views
from datagen.evaluate.protocol import Plan, Planner, PlannerContext
from datagen.evaluate.situation import Situation


class AllPlanner:
    name = "all"
    uses_refinement = False

    def plan(self, situation: Situation) -> Plan:
        return Plan(views=tuple(v for v in range(situation.scene.num_views) if v != situation.initial_view))


Chooser = Callable[[Situation, int], tuple[int, ...]]
"""How a baseline picks ``count`` views other than the initial one in a situation."""


def random_views(situation: Situation, count: int) -> tuple[int, ...]:
    """``count`` uniform views other than the initial one (all of them if fewer), from the situation's stream."""
    others = [v for v in range(situation.scene.num_views) if v != situation.initial_view]
    chosen = situation.rng().choice(len(others), size=min(count, len(others)), replace=False)
    return tuple(sorted(others[i] for i in chosen))


def spread_chooser(situation: Situation, count: int) -> tuple[int, ...]:
    """``count`` views spread far from the initial one and from each other (`fixed.spread_views`)."""
    return spread_views(situation.scene.positions, situation.initial_view, count)


def fixed_chooser(plans: FixedPlans | None, spec: str) -> Chooser:
    """The training dataset's best constant set of ``count`` views; refused without a dataset to choose from."""
    if plans is None:
        raise PlannerError(
            f"planner {spec!r} plays the best fixed view sets of a training dataset: give {FIXED_OPTION} URL"
        )
    return lambda situation, count: plans.plan(count, situation.initial_view).views


BASELINES = ("random", "fixed", "spread")
"""Planners that never look at the object: chance, the best constant plan, a data-free spread."""


class BaselinePlanner:
    """A baseline (`BASELINES`) taking as many views as the oracle (``NAME``) or K in all (``NAME:K``)."""

    def __init__(self, kind: str, choose: Chooser, total_views: int | None = None) -> None:
        self.kind = kind
        self.choose = choose
        self.total_views = total_views
        self.name = kind if total_views is None else f"{kind}:{total_views}"
        self.uses_refinement = total_views is None

    def plan(self, situation: Situation) -> Plan:
        wanted = self.total_views - 1 if self.total_views is not None else situation.oracle_label().label.bit_count()
        return Plan(views=self.choose(situation, wanted), at_count=lambda c: self.choose(situation, c))


class RandomPlanner(BaselinePlanner):
    """Seeded uniform views other than the initial one, from the situation's own stream."""

    def __init__(self, total_views: int | None = None) -> None:
        super().__init__("random", random_views, total_views)


@dataclass
class MatchedPlanner:
    """``KIND:match=SPEC``: a baseline taking exactly as many views as planner SPEC chose in the same situation.

    The run evaluates SPEC first and hands its plan's view count over with `taking` (a planner is asked
    one situation at a time and sees no other planner's answer). What is matched is the number of
    distinct views SPEC's plan chose, the initial view excluded, before any budget: both runs then meet
    the same --budget-views/--budget-moves cut afterwards, like every planner, so a budget never decides
    how many views the baseline gets. Random views come from the situation's own stream (as
    `RandomPlanner`'s), so they depend neither on worker count nor on planner order; the planner reads the
    refined input iff SPEC does, so both run under the same refiner label.
    """

    name: str
    wanted: str
    """SPEC as the user gave it: another planner's spec, or a prefix of exactly one."""
    choose: Chooser = random_views
    kind: str = "random"
    matched: str | None = None
    """The full spec of the planner it matches, once `match_planners` has bound it."""
    uses_refinement: bool = True
    count: int | None = None
    """The matched planner's view count in the situation at hand (`taking`)."""

    def matching(self, matched: Planner) -> MatchedPlanner:
        """This planner bound to the planner it matches."""
        return replace(self, matched=matched.name, uses_refinement=matched.uses_refinement)

    def taking(self, count: int) -> MatchedPlanner:
        """This planner for one situation where the matched planner chose ``count`` views."""
        return replace(self, count=count)

    def plan(self, situation: Situation) -> Plan:
        if self.count is None:
            raise ValueError(f"planner {self.name} plans only with the matched planner's view count (`taking`)")
        return Plan(views=self.choose(situation, self.count), at_count=lambda c: self.choose(situation, c))


MatchedRandomPlanner = MatchedPlanner
"""``random:match=SPEC`` (the first matched baseline)."""


def is_baseline(planner: Planner) -> bool:
    """A planner that never looks at the object (chance, fixed, spread, every view): it gets no lift."""
    return isinstance(planner, BaselinePlanner | MatchedPlanner | AllPlanner)


def chosen_count(views: Sequence[int], initial_view: int) -> int:
    """How many views a plan chose: distinct views, the initial one excluded (what a matched random takes)."""
    return len(set(views) - {initial_view})


CHOOSERS: dict[str, Callable[[PlannerContext, str], Chooser]] = {
    "random": lambda context, spec: random_views,
    "fixed": lambda context, spec: fixed_chooser(context.fixed, spec),
    "spread": lambda context, spec: spread_chooser,
}
"""How each baseline (`BASELINES`) picks its views, given the evaluation's context and the planner's spec."""


def _chooser(kind: str, spec: str, context: PlannerContext) -> Chooser:
    return CHOOSERS[kind](context, spec)


def baseline_at_count(kind: str, context: PlannerContext) -> MatchedPlanner | None:
    """The unbound matched baseline ``kind`` (random, fixed or spread) that gives every run a lift, None
    where it cannot be built (fixed without a training dataset)."""
    try:
        chooser = _chooser(kind, kind, context)
    except PlannerError:  # its chooser cannot be made here (fixed plans without a training dataset)
        return None
    return MatchedPlanner(f"{kind}:match", "", chooser, kind)


def match_planners(planners: Sequence[Planner]) -> list[Planner]:
    """The planners, in their order, with every ``KIND:match=SPEC`` bound to the planner SPEC names."""
    return [p.matching(_matched(p, planners)) if isinstance(p, MatchedPlanner) else p for p in planners]


def _matched(planner: MatchedPlanner, planners: Sequence[Planner]) -> Planner:
    """The one planner SPEC names, exactly or as the prefix of a single spec; otherwise one error line naming
    the choices (a matched baseline matches neither itself nor another matched baseline: their counts are
    borrowed, not chosen)."""
    choices = {p.name: p for p in planners if not isinstance(p, MatchedPlanner)}
    names = sorted(choices)
    listed = ", ".join(names) if names else "none: add the planner to match"
    found = [n for n in names if n == planner.wanted] or [n for n in names if n.startswith(planner.wanted)]
    if len(found) == 1:
        return choices[found[0]]
    if found:
        problem = f"{planner.wanted!r} is the start of {len(found)} planners; give one in full"
    elif any(isinstance(p, MatchedPlanner) and p.name.startswith(planner.wanted) for p in planners):
        problem = "a matched baseline cannot match itself or another :match planner"
    else:
        problem = f"{planner.wanted!r} names no other planner of this run"
    raise PlannerError(f"planner {planner.name!r}: {problem}; choose one of {listed}")
