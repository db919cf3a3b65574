"""Planners `datagen evaluate` compares, behind one small interface.

A planner answers a `Situation` with a `Plan`: either a one-shot set (visited along the shortest open
path) or an ordered sequence (an iterative chooser that already decided the order). Trained networks
plug in as a `ViewScorer` (`schemas.planning`: refined cloud + view state in, one probability per view
out) wrapped by `ScoredPlanner`, which keeps the views above 0.5 as the paper does, or lets a `DecodingScorer` turn the
probabilities into views its own way (a named decoding). Baselines:

- ``oracle``: the generator's exact label for this very case, what a perfect network trained on the
  dataset would predict; ``oracle:SETTING=V[,...]`` labels under other label settings (``alpha``,
  ``objective``, ``budget`` for max_coverage, ``tau`` for partial_cover: docs/pipeline.md section 7.5),
  so one evaluation compares label objectives;
- ``greedy`` / ``greedy:K``: next-best view by true new surface, one view at a time, until no view
  adds surface (or K views in all, the initial one included): the search-based NBV bound;
- ``gain`` / ``gain:K``: the same played as a next-best-view planner (`datagen.evaluate.sequential`)
  with the true gains as its scorer: asked after every view, 10 views in all by default;
- ``random`` / ``random:K``: seeded uniform views, as many as the oracle's (or K in all);
- ``fixed`` / ``fixed:K``: the best constant view set of that size, chosen once from a training
  dataset (``--fixed-from``, `datagen.evaluate.fixed`): the floor a planner that looks at the object
  must beat;
- ``spread`` / ``spread:K``: views spread far apart from the initial one, needing no data;
- ``random:match=SPEC``, ``fixed:match=SPEC``, ``spread:match=SPEC``: that baseline with as many views as
  planner SPEC of the same run chose in the same situation (`match_planners`). Every other planner's
  runs also carry random's, fixed's and spread's coverage at their own view count (their lifts);
- ``all``: every candidate view.

Any other ``NAME:ARG`` is a planner plugin: the `schemas.planning.ScorerFactory` an installed distribution
registers as entry point NAME in the group ``datagen.planners`` (`PLANNER_ENTRY_POINTS`), imported only
when asked for and called with ARG once per process (`plugin_scorer`); a one-shot `ViewScorer` is
wrapped by `ScoredPlanner`, a `NextViewScorer` played step by step by `SequentialPlanner`;
``NAME+DECODE:ARG`` plans with the scorer's decoding DECODE instead of its default. The `osvp`
training package is one such plugin: ``osvp:FILE`` loads an `osvp train` checkpoint.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint

import numpy as np

from datagen.errors import PlannerError
from datagen.evaluate.baselines import (
    CHOOSERS,
    AllPlanner,
    BaselinePlanner,
    Chooser,
    MatchedPlanner,
    RandomPlanner,
)
from datagen.evaluate.oracle import OraclePlanner, oracle_setting_fields, oracle_settings
from datagen.evaluate.protocol import MATCH_PREFIX, Plan, Planner, PlannerContext
from datagen.evaluate.scored import ScoredPlanner, plugin_scorer
from datagen.evaluate.situation import Situation
from schemas.planning import PLANNER_ENTRY_POINTS, NextViewScorer
from schemas.registry import Registry, plugin_source


class GreedyPlanner:
    """Next-best view by the true new surface each candidate would add; ties go to the lowest view id."""

    uses_refinement = False

    def __init__(self, total_views: int | None = None) -> None:
        self.total_views = total_views
        self.name = "greedy" if total_views is None else f"greedy:{total_views}"

    def plan(self, situation: Situation) -> Plan:
        scene = situation.scene
        seen = scene.seen([situation.initial_view])
        taken = [situation.initial_view]
        limit = scene.num_views if self.total_views is None else self.total_views
        while len(taken) < limit:
            gains = [
                -1 if v in taken else int(np.count_nonzero(~seen[scene.view_columns[v]]))
                for v in range(scene.num_views)
            ]
            best = int(np.argmax(gains))
            if gains[best] <= 0 and self.total_views is None:
                break
            if gains[best] < 0:
                break
            taken.append(best)
            seen[scene.view_columns[best]] = True
        return Plan(views=tuple(taken[1:]), ordered=True)


@dataclass(frozen=True)
class PlannerSpec:
    """A planner as named on the command line: ``NAME[+DECODING][:ARGUMENT]``."""

    text: str
    name: str
    argument: str = ""
    decoding: str | None = None

    @classmethod
    def parse(cls, text: str) -> PlannerSpec:
        name, colon, argument = text.partition(":")
        if colon and not argument:
            raise PlannerError(f"planner {text!r} names nothing after ':'; choose {planner_help()}")
        base, plus, decoding = name.partition("+")
        if plus and not decoding:
            raise PlannerError(f"planner {text!r} names no decoding after '+'; give {base}+DECODING:{argument}")
        return cls(text, base, argument, decoding if plus else None)


PlannerBuilder = Callable[[PlannerSpec, PlannerContext], Planner]
"""Builds the planner a spec names (refusing an argument or decoding it cannot take: `PlannerError`)."""


@dataclass(frozen=True)
class PlannerKind:
    """One planner name: how it is built, how it is written, and where it comes from."""

    name: str
    build: PlannerBuilder
    usage: str
    """How to write it, e.g. ``greedy, greedy:K``."""
    source: str = "built-in"
    plugin: EntryPoint | None = None
    """The entry point of a plug-in kind (None for a built-in)."""


def _plugin_kind(plugin: EntryPoint) -> PlannerKind:
    """An installed plug-in's planner kind, its module imported only when a planner of it is built."""
    return PlannerKind(plugin.name, _plugin_builder(plugin), f"{plugin.name}:ARG", plugin_source(plugin), plugin)


PLANNERS: Registry[PlannerKind] = Registry("planner", PLANNER_ENTRY_POINTS, error=PlannerError, adapt=_plugin_kind)
"""Every planner one can name: the built-ins (`register_planner`), then each installed plug-in (an
entry point of `PLANNER_ENTRY_POINTS`, the first of a name; one named like a built-in is never used)."""


def register_planner(name: str, usage: str) -> Callable[[PlannerBuilder], PlannerBuilder]:
    """Register a built-in planner kind under ``name`` (as a plugin registers a scorer factory under its
    entry point's name)."""

    def register(build: PlannerBuilder) -> PlannerBuilder:
        PLANNERS.register(name, PlannerKind(name, build, usage))
        return build

    return register


def planner_kinds() -> dict[str, PlannerKind]:
    """Every planner one can name, in one mapping: the built-ins, then each installed plugin."""
    return dict(PLANNERS.items())


def plugin_usage(kind: PlannerKind) -> str:
    """How to write a plug-in's planners: ``NAME:C`` for each of its factory's ``choices`` (osvp's
    ``shipped:nbv``), else ``NAME:ARG``. Loads the plug-in, so only help being shown asks for it; one
    that cannot be loaded keeps ``NAME:ARG`` (naming it fails with its own line)."""
    if kind.plugin is None:
        return kind.usage
    try:
        choices = getattr(kind.plugin.load(), "choices", None)
    except Exception:  # a broken third-party plug-in must not break --help
        return kind.usage
    if not choices:
        return kind.usage
    return ", ".join(f"{kind.name}:{choice}" for choice in choices)


def installed_plugins() -> dict[str, PlannerKind]:
    """The planner kinds that come from plugins, by name."""
    return {name: kind for name, kind in planner_kinds().items() if kind.source != "built-in"}


def lookup_planner(name: str, spec: str | None = None) -> PlannerKind:
    """The planner kind called ``name``, built-in or plugin; one `PlannerError` line naming the choices."""
    found = PLANNERS.get(name)
    if found is None:
        raise PlannerError(f"unknown planner {spec or name!r}; choose {planner_help()}")
    return found


def planner_help(kinds: dict[str, PlannerKind] | None = None, load: bool = False) -> str:
    """The planners one can name: the built-ins' usages, then ``NAME:ARG`` of each installed plugin
    (with ``load``, the names each plugin offers: `plugin_usage`)."""
    kinds = planner_kinds() if kinds is None else kinds
    builtin = ", ".join(kind.usage for kind in kinds.values() if kind.source == "built-in")
    plugins = sorted(plugin_usage(kind) if load else kind.usage for kind in kinds.values() if kind.source != "built-in")
    listed = ", ".join(plugins) if plugins else f"none installed in {PLANNER_ENTRY_POINTS!r}"
    return f"{builtin}, or a plugin's NAME:ARG or NAME+DECODING:ARG ({listed})"


def make_planner(spec: str, context: PlannerContext | None = None) -> Planner:
    """The planner a command-line name stands for; `PlannerError` names the choices otherwise.

    A ``KIND:match=SPEC`` comes back unbound: `match_planners` binds it to a planner of the same run.
    """
    parsed = PlannerSpec.parse(spec)
    return lookup_planner(parsed.name, spec).build(parsed, context or PlannerContext())


def _plugin_builder(plugin: EntryPoint) -> PlannerBuilder:
    def build(spec: PlannerSpec, context: PlannerContext) -> Planner:
        if not spec.argument:
            raise PlannerError(f"planner {spec.text!r}: give {plugin.name}:ARG (for example a checkpoint)")
        scorer = plugin_scorer(plugin, spec.argument, spec.text)
        if isinstance(scorer, NextViewScorer):
            from datagen.evaluate.sequential import SequentialPlanner

            _plain(spec, f"{plugin.name}:ARG")
            return SequentialPlanner(spec.text, lambda situation: scorer, context.budget_views)
        return ScoredPlanner(spec.text, scorer, decoding=spec.decoding)

    return build


def _plain(spec: PlannerSpec, usage: str) -> None:
    """Refuse a decoding: only scored planners have decodings."""
    if spec.decoding is not None:
        raise PlannerError(f"planner {spec.text!r}: only a plugin's scorer takes +DECODING; write {usage}")


@register_planner("oracle", f"oracle, oracle:SETTING=V ({', '.join(oracle_setting_fields())})")
def _oracle(spec: PlannerSpec, context: PlannerContext) -> Planner:
    _plain(spec, "oracle")
    changes = oracle_settings(spec.text, spec.argument) if spec.argument else None
    return OraclePlanner(context.config, changes, spec.text)


@register_planner("gain", "gain, gain:K")
def _gain(spec: PlannerSpec, context: PlannerContext) -> Planner:
    from datagen.evaluate.sequential import SequentialPlanner, TrueGains

    _plain(spec, "gain:K")
    total = _view_count(spec.text, spec.argument) if spec.argument else context.budget_views
    return SequentialPlanner(spec.text, lambda situation: TrueGains(situation.scene), total)


@register_planner("greedy", "greedy, greedy:K")
def _greedy(spec: PlannerSpec, context: PlannerContext) -> Planner:
    _plain(spec, "greedy:K")
    return GreedyPlanner(_view_count(spec.text, spec.argument) if spec.argument else None)


def _baseline(
    kind: str,
    choose: Callable[[PlannerSpec, PlannerContext], Chooser],
    make: Callable[[str, Chooser, int | None], Planner] = BaselinePlanner,
) -> PlannerBuilder:
    def build(spec: PlannerSpec, context: PlannerContext) -> Planner:
        _plain(spec, f"{kind}:K")
        chooser = choose(spec, context)
        if spec.argument.startswith(MATCH_PREFIX):
            wanted = spec.argument.removeprefix(MATCH_PREFIX)
            if not wanted:
                raise PlannerError(f"planner {spec.text!r} names no planner after '='; give {kind}:match=PLANNER")
            return MatchedPlanner(spec.text, wanted, chooser, kind)
        total = _view_count(spec.text, spec.argument) if spec.argument else None
        return make(kind, chooser, total)

    return build


register_planner("random", "random, random:K, random:match=PLANNER")(
    _baseline("random", lambda s, c: CHOOSERS["random"](c, s.text), lambda kind, chooser, total: RandomPlanner(total))
)


register_planner("fixed", "fixed, fixed:K, fixed:match=PLANNER (with --fixed-from)")(
    _baseline("fixed", lambda s, c: CHOOSERS["fixed"](c, s.text))
)


register_planner("spread", "spread, spread:K, spread:match=PLANNER")(
    _baseline("spread", lambda s, c: CHOOSERS["spread"](c, s.text))
)


@register_planner("all", "all")
def _all(spec: PlannerSpec, context: PlannerContext) -> Planner:
    if spec.argument or spec.decoding:
        raise PlannerError(f"planner {spec.text!r}: 'all' takes no argument; write all")
    return AllPlanner()


def _view_count(spec: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise PlannerError(f"planner {spec!r}: K must be a whole number of views >= 1 (the initial view counts)")
    return value
