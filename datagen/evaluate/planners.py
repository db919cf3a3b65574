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

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from importlib.metadata import EntryPoint, entry_points

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from datagen.errors import DatagenError, PlannerError
from datagen.evaluate.fixed import FIXED_OPTION, FixedPlans, spread_views
from datagen.evaluate.grids import SceneGrids, empty_log_odds, inserted, occupancy_grid
from datagen.evaluate.protocol import Plan, Planner, one_line
from datagen.evaluate.situation import Situation, needs_refinement
from datagen.pipeline.setcover import mask_to_views
from schemas.config import GenerationConfig
from schemas.objectives import OBJECTIVES, UnknownObjective, objective_named
from schemas.planning import PLANNER_ENTRY_POINTS, DecodingScorer, NextViewScorer, ScorerFactory, ViewScorer

CHOICE_THRESHOLD = 0.5
"""A view is chosen when its probability exceeds this (the paper's rule)."""


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


@dataclass(frozen=True)
class PlannerContext:
    """What building a planner may need besides its spec: the evaluation's config (the oracle's label
    settings) and the fixed plans chosen from a training dataset (``--fixed-from``)."""

    config: GenerationConfig = field(default_factory=GenerationConfig)
    fixed: FixedPlans | None = None
    budget_views: int | None = None
    """``--budget-views``: how many views in all a next-best-view planner plays (default 10)."""


MATCH_PREFIX = "match="
"""``random:match=SPEC``: the argument that names the planner whose view count a random planner takes."""


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


class AllPlanner:
    name = "all"
    uses_refinement = False

    def plan(self, situation: Situation) -> Plan:
        return Plan(views=tuple(v for v in range(situation.scene.num_views) if v != situation.initial_view))


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


class ScoredPlanner:
    """A trained network as a planner: the views whose probability exceeds 0.5, or those its scorer's
    decoding selects (a `DecodingScorer`), the views already taken excluded."""

    uses_refinement = True

    def __init__(self, name: str, scorer: ViewScorer, decoding: str | None = None) -> None:
        _check_decoding(name, scorer, decoding)
        self.name = name
        self.scorer = scorer
        self.decoding = decoding
        """None: the scorer's default (the paper's 0.5 rule for a scorer without decodings)."""
        self.grids = SceneGrids() if getattr(scorer, "uses_grid", False) else None
        """A grid planner's (SCVP's manner) scene grids: it is shown the initial view's occupancy grid
        and the cloud that view observed, and needs no refinement."""
        self.uses_refinement = self.grids is None

    def plan(self, situation: Situation) -> Plan:
        if self.grids is None:
            request = situation.request()
            cloud = request.observed if getattr(self.scorer, "source", "points") == "observed" else request.points
            view_state = request.view_state
            scores = self.scorer.view_probabilities(cloud, view_state)
        else:
            view_state = np.zeros(situation.scene.num_views, dtype=np.float32)
            view_state[situation.initial_view] = 1.0
            cloud = situation.scene.observed_points([situation.initial_view])
            grid = occupancy_grid(inserted(empty_log_odds(), self.grids.of(situation), [situation.initial_view]))
            scores = self.scorer.view_probabilities(cloud, view_state, grid=grid)  # type: ignore[call-arg]
        probabilities = np.asarray(scores, dtype=np.float64)
        self._check_length("probabilities", probabilities, view_state.size)
        take = self._select(probabilities, view_state)
        open_views = np.asarray(view_state) == 0
        chosen = np.flatnonzero(take & open_views)
        ranking = tuple(int(v) for v in np.argsort(-probabilities, kind="stable") if open_views[v])
        return Plan(views=tuple(int(v) for v in chosen), probabilities=probabilities, at_count=lambda c: ranking[:c])

    def _select(
        self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.bool_]:
        if not isinstance(self.scorer, DecodingScorer):
            return probabilities > CHOICE_THRESHOLD
        try:
            take = np.asarray(self.scorer.select_views(probabilities, view_state, self.decoding), dtype=bool)
        except ValueError as exc:
            raise PlannerError(f"planner {self.name}: {exc}") from None
        self._check_length("view choices", take, probabilities.size)
        return take

    def _check_length(self, what: str, values: npt.NDArray[np.generic], num_views: int) -> None:
        if values.shape != (num_views,):
            raise PlannerError(
                f"planner {self.name} returned {values.shape} {what} for {num_views} views; "
                "its checkpoint was trained for another view space"
            )


def _check_decoding(name: str, scorer: ViewScorer, decoding: str | None) -> None:
    """Refuse a decoding the scorer cannot apply before any imaging (``threshold=0.3`` is checked as
    ``threshold``); a scorer that lists no ``decodings`` is asked when it plans."""
    if decoding is None:
        return
    if not isinstance(scorer, DecodingScorer):
        raise PlannerError(f"planner {name!r}: this scorer has no decodings; drop '+{decoding}' for its 0.5 rule")
    accepted = getattr(scorer, "decodings", None)
    if accepted is not None and decoding.partition("=")[0] not in accepted:
        raise PlannerError(f"planner {name!r}: unknown decoding {decoding!r}; choose {', '.join(accepted)}")


_SCORERS: dict[tuple[EntryPoint, str], ViewScorer | NextViewScorer] = {}
"""The scorers built in this process, by plugin and argument (`plugin_scorer`)."""


def plugin_scorer(plugin: EntryPoint, argument: str, spec: str) -> ViewScorer | NextViewScorer:
    """The scorer a planner plugin's factory builds for ARGUMENT (``spec`` names the planner in errors).

    Built once per process and plugin and argument, however many objects and situations ask (a
    checkpoint is read once, not once per object): a file changed under the same path in the same
    process is not read again. Every failure is one `PlannerError` line: a plugin that cannot be
    imported (naming its distribution), an argument its factory refuses (its `DatagenError` goes
    through as it is), or a factory that returns neither a `ViewScorer` nor a `NextViewScorer`.
    """
    key = (plugin, argument)
    if key not in _SCORERS:
        _SCORERS[key] = _build_scorer(plugin, argument, spec)
    return _SCORERS[key]


def _build_scorer(plugin: EntryPoint, argument: str, spec: str) -> ViewScorer | NextViewScorer:
    dist = plugin.dist
    source = f"distribution {dist.name} {dist.version}" if dist is not None else "its distribution"
    try:
        factory: ScorerFactory = plugin.load()
    except Exception as exc:  # any import-time failure of third-party code: one line, not a traceback
        raise PlannerError(
            f"planner plugin {plugin.name!r} ({plugin.value}, {source}) cannot be imported: {one_line(exc)}"
        ) from None
    try:
        scorer = factory(argument)
    except DatagenError:
        raise
    except (ValueError, OSError) as exc:
        raise PlannerError(f"planner {spec!r}: {one_line(exc, named=False)}") from None
    if not isinstance(scorer, ViewScorer | NextViewScorer):
        raise PlannerError(
            f"planner {spec!r}: plugin {plugin.name!r} ({plugin.value}, {source}) returned a "
            f"{type(scorer).__name__}, not a scorer with view_probabilities(points, view_state) or "
            "next_view_scores(observation)"
        )
    return scorer


# ---------------------------------------------------------------------------------------------------------
# the registry: every planner name, built-in or plugin, found by one lookup
# ---------------------------------------------------------------------------------------------------------


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


BUILTIN_PLANNERS: dict[str, PlannerKind] = {}
"""The planners datagen itself provides, by name (`register_planner`); a plugin never takes one's name."""


def register_planner(name: str, usage: str) -> Callable[[PlannerBuilder], PlannerBuilder]:
    """Register a built-in planner kind under ``name`` (as a plugin registers a scorer factory under its
    entry point's name)."""

    def register(build: PlannerBuilder) -> PlannerBuilder:
        BUILTIN_PLANNERS[name] = PlannerKind(name, build, usage)
        return build

    return register


def planner_kinds() -> dict[str, PlannerKind]:
    """Every planner one can name, in one mapping: the built-ins, then each installed plugin (entry
    points of group `PLANNER_ENTRY_POINTS`, the first of a name; one named like a built-in is never
    used), imported only when a planner of it is built."""
    kinds = dict(BUILTIN_PLANNERS)
    for plugin in entry_points(group=PLANNER_ENTRY_POINTS):
        if plugin.name not in kinds:
            dist = plugin.dist
            source = f"distribution {dist.name} {dist.version}" if dist is not None else "a plugin"
            kinds[plugin.name] = PlannerKind(plugin.name, _plugin_builder(plugin), f"{plugin.name}:ARG", source)
    return kinds


def installed_plugins() -> dict[str, PlannerKind]:
    """The planner kinds that come from plugins, by name."""
    return {name: kind for name, kind in planner_kinds().items() if kind.source != "built-in"}


def lookup_planner(name: str, spec: str | None = None) -> PlannerKind:
    """The planner kind called ``name``, built-in or plugin; one `PlannerError` line naming the choices."""
    kinds = planner_kinds()
    if name not in kinds:
        raise PlannerError(f"unknown planner {spec or name!r}; choose {planner_help(kinds)}")
    return kinds[name]


def planner_help(kinds: dict[str, PlannerKind] | None = None) -> str:
    """The planners one can name: the built-ins' usages, then ``NAME:ARG`` of each installed plugin."""
    kinds = planner_kinds() if kinds is None else kinds
    builtin = ", ".join(kind.usage for kind in kinds.values() if kind.source == "built-in")
    plugins = sorted(kind.usage for kind in kinds.values() if kind.source != "built-in")
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


@register_planner("oracle", "oracle, oracle:SETTING=V (alpha, objective, budget, tau)")
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


def _baseline(kind: str, choose: Callable[[PlannerSpec, PlannerContext], Chooser]) -> PlannerBuilder:
    def build(spec: PlannerSpec, context: PlannerContext) -> Planner:
        _plain(spec, f"{kind}:K")
        chooser = choose(spec, context)
        if spec.argument.startswith(MATCH_PREFIX):
            wanted = spec.argument.removeprefix(MATCH_PREFIX)
            if not wanted:
                raise PlannerError(f"planner {spec.text!r} names no planner after '='; give {kind}:match=PLANNER")
            return MatchedPlanner(spec.text, wanted, chooser, kind)
        total = _view_count(spec.text, spec.argument) if spec.argument else None
        return RandomPlanner(total) if kind == "random" else BaselinePlanner(kind, chooser, total)

    return build


register_planner("random", "random, random:K, random:match=PLANNER")(_baseline("random", lambda s, c: random_views))
register_planner("fixed", "fixed, fixed:K, fixed:match=PLANNER (with --fixed-from)")(
    _baseline("fixed", lambda s, c: fixed_chooser(c.fixed, s.text))
)
register_planner("spread", "spread, spread:K, spread:match=PLANNER")(_baseline("spread", lambda s, c: spread_chooser))


@register_planner("all", "all")
def _all(spec: PlannerSpec, context: PlannerContext) -> Planner:
    if spec.argument or spec.decoding:
        raise PlannerError(f"planner {spec.text!r}: 'all' takes no argument; write all")
    return AllPlanner()


def _chooser(kind: str, spec: str, context: PlannerContext) -> Chooser:
    if kind == "fixed":
        return fixed_chooser(context.fixed, spec)
    return spread_chooser if kind == "spread" else random_views


def baseline_at_count(kind: str, context: PlannerContext) -> MatchedPlanner | None:
    """The unbound matched baseline ``kind`` (random, fixed or spread) that gives every run a lift, None
    where it cannot be built (fixed without a training dataset)."""
    if kind == "fixed" and context.fixed is None:
        return None
    return MatchedPlanner(f"{kind}:match", "", _chooser(kind, kind, context), kind)


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


def _view_count(spec: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise PlannerError(f"planner {spec!r}: K must be a whole number of views >= 1 (the initial view counts)")
    return value
