"""Planners `datagen evaluate` compares, behind one small interface.

A planner answers a `Situation` with a `Plan`: either a one-shot set (visited along the shortest open
path) or an ordered sequence (an iterative chooser that already decided the order). Trained networks
plug in as a `ViewScorer` (`schemas.planning`: refined cloud + view state in, one probability per view
out) wrapped by `ScoredPlanner`, which keeps the views above 0.5 as the paper does, or lets a `DecodingScorer` turn the
probabilities into views its own way (a named decoding). Baselines:

- ``oracle``: the generator's exact label for this very case, what a perfect network trained on the
  dataset would predict;
- ``greedy`` / ``greedy:K``: next-best view by true new surface, one view at a time, until no view
  adds surface (or K views in all, the initial one included): the search-based NBV bound;
- ``random`` / ``random:K``: seeded uniform views, as many as the oracle's (or K in all);
- ``random:match=SPEC``: seeded uniform views, as many as planner SPEC of the same run chose in the same
  situation, so a trained planner is judged against chance at equal views (`match_planners`);
- ``all``: every candidate view.

Any other ``NAME:ARG`` is a planner plugin: the `schemas.planning.ScorerFactory` an installed distribution
registers as entry point NAME in the group ``datagen.planners`` (`PLANNER_ENTRY_POINTS`), imported only
when asked for and called with ARG once per process (`plugin_scorer`); ``NAME+DECODE:ARG`` plans with the
scorer's decoding DECODE instead of its default. The `osvp` training package is one such plugin:
``osvp:FILE`` loads an `osvp train` checkpoint.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from importlib.metadata import EntryPoint, entry_points
from typing import Protocol

import numpy as np
import numpy.typing as npt

from datagen.errors import DatagenError, PlannerError
from datagen.evaluate.situation import Situation
from datagen.pipeline.setcover import mask_to_views
from schemas.planning import PLANNER_ENTRY_POINTS, DecodingScorer, ScorerFactory, ViewScorer

CHOICE_THRESHOLD = 0.5
"""A view is chosen when its probability exceeds this (the paper's rule)."""

BUILTIN_PLANNERS = ("oracle", "greedy", "random", "all")
"""Names a plugin cannot take: ``NAME:ARG`` with one of these is never looked up among the entry points."""
BUILTIN_HELP = "oracle, greedy, greedy:K, random, random:K, random:match=PLANNER, all"


def installed_plugins() -> dict[str, EntryPoint]:
    """The planner plugins of this environment by NAME: entry points of group `PLANNER_ENTRY_POINTS`
    (the first one of a name; one named like a built-in planner is never used)."""
    found: dict[str, EntryPoint] = {}
    for plugin in entry_points(group=PLANNER_ENTRY_POINTS):
        if plugin.name not in BUILTIN_PLANNERS:
            found.setdefault(plugin.name, plugin)
    return found


def planner_help(plugins: Sequence[str] | None = None) -> str:
    """The planners one can name: the built-ins, then ``NAME:ARG`` of each installed plugin."""
    names = sorted(installed_plugins() if plugins is None else plugins)
    listed = ", ".join(f"{name}:ARG" for name in names) if names else f"none installed in {PLANNER_ENTRY_POINTS!r}"
    return f"{BUILTIN_HELP}, or a plugin's NAME:ARG or NAME+DECODING:ARG ({listed})"


PLANNER_HELP = planner_help()
"""`planner_help` of the plugins installed when this module was imported."""
MATCH_PREFIX = "match="
"""``random:match=SPEC``: the argument that names the planner whose view count a random planner takes."""


@dataclass(frozen=True)
class Plan:
    """A planner's answer: the views to take after the initial one."""

    views: tuple[int, ...]
    ordered: bool = False
    """True: visit in this order; False: a one-shot set, ordered by the shortest open path."""
    probabilities: npt.NDArray[np.float64] | None = None


class Planner(Protocol):
    name: str
    uses_refinement: bool
    """Whether the planner reads the refined input or the generator's label (the scene must be refined)."""

    def plan(self, situation: Situation) -> Plan: ...


class OraclePlanner:
    name = "oracle"
    uses_refinement = True

    def plan(self, situation: Situation) -> Plan:
        return Plan(views=mask_to_views(situation.oracle_label().label))


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


class RandomPlanner:
    """Uniform views other than the initial one, from the situation's own seeded stream."""

    def __init__(self, total_views: int | None = None) -> None:
        self.total_views = total_views
        self.name = "random" if total_views is None else f"random:{total_views}"
        self.uses_refinement = total_views is None

    def plan(self, situation: Situation) -> Plan:
        wanted = self.total_views - 1 if self.total_views is not None else situation.oracle_label().label.bit_count()
        return Plan(views=random_views(situation, wanted))


@dataclass
class MatchedRandomPlanner:
    """``random:match=SPEC``: uniform views, exactly as many as planner SPEC chose in the same situation.

    The run evaluates SPEC first and hands its plan's view count over with `taking` (a planner is asked
    one situation at a time and sees no other planner's answer). What is matched is the number of
    distinct views SPEC's plan chose, the initial view excluded, before any budget: both runs then meet
    the same --budget-views/--budget-moves cut afterwards, like every planner, so a budget never decides
    how many views chance gets. The views come from the situation's own stream (as `RandomPlanner`'s),
    so they depend neither on worker count nor on planner order; the planner reads the refined input iff
    SPEC does, so both run under the same refiner label.
    """

    name: str
    wanted: str
    """SPEC as the user gave it: another planner's spec, or a prefix of exactly one."""
    matched: str | None = None
    """The full spec of the planner it matches, once `match_planners` has bound it."""
    uses_refinement: bool = True
    count: int | None = None
    """The matched planner's view count in the situation at hand (`taking`)."""

    def matching(self, matched: Planner) -> MatchedRandomPlanner:
        """This planner bound to the planner it matches."""
        return replace(self, matched=matched.name, uses_refinement=matched.uses_refinement)

    def taking(self, count: int) -> MatchedRandomPlanner:
        """This planner for one situation where the matched planner chose ``count`` views."""
        return replace(self, count=count)

    def plan(self, situation: Situation) -> Plan:
        if self.count is None:
            raise ValueError(f"planner {self.name} plans only with the matched planner's view count (`taking`)")
        return Plan(views=random_views(situation, self.count))


def random_views(situation: Situation, count: int) -> tuple[int, ...]:
    """``count`` uniform views other than the initial one (all of them if fewer), from the situation's stream."""
    others = [v for v in range(situation.scene.num_views) if v != situation.initial_view]
    chosen = situation.rng().choice(len(others), size=min(count, len(others)), replace=False)
    return tuple(sorted(others[i] for i in chosen))


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

    def plan(self, situation: Situation) -> Plan:
        request = situation.request()
        cloud = request.observed if getattr(self.scorer, "source", "points") == "observed" else request.points
        probabilities = np.asarray(self.scorer.view_probabilities(cloud, request.view_state), dtype=np.float64)
        self._check_length("probabilities", probabilities, request.num_views)
        take = self._select(probabilities, request.view_state)
        chosen = np.flatnonzero(take & (np.asarray(request.view_state) == 0))
        return Plan(views=tuple(int(v) for v in chosen), probabilities=probabilities)

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


_SCORERS: dict[tuple[EntryPoint, str], ViewScorer] = {}
"""The scorers built in this process, by plugin and argument (`plugin_scorer`)."""


def plugin_scorer(name: str, argument: str, spec: str) -> ViewScorer:
    """The scorer planner plugin NAME builds for ARGUMENT (``spec`` names the planner in errors).

    Built once per process and plugin and argument, however many objects and situations ask (a
    checkpoint is read once, not once per object): a file changed under the same path in the same
    process is not read again. Every failure is one `PlannerError` line: no such plugin (naming the
    installed ones), a plugin that cannot be imported (naming its distribution), an argument its factory
    refuses (its `DatagenError` goes through as it is), or a factory that returns no `ViewScorer`.
    """
    plugins = installed_plugins()
    plugin = plugins.get(name)
    if plugin is None:
        if name == "osvp":
            raise PlannerError(f"planner {spec!r} needs the osvp package; install it with `pip install ./osvp`")
        raise PlannerError(f"unknown planner {spec!r}; choose {planner_help(list(plugins))}")
    key = (plugin, argument)
    if key not in _SCORERS:
        _SCORERS[key] = _build_scorer(plugin, argument, spec)
    return _SCORERS[key]


def _build_scorer(plugin: EntryPoint, argument: str, spec: str) -> ViewScorer:
    dist = plugin.dist
    source = f"distribution {dist.name} {dist.version}" if dist is not None else "its distribution"
    try:
        factory: ScorerFactory = plugin.load()
    except Exception as exc:  # any import-time failure of third-party code: one line, not a traceback
        raise PlannerError(
            f"planner plugin {plugin.name!r} ({plugin.value}, {source}) cannot be imported: {_one_line(exc)}"
        ) from None
    try:
        scorer = factory(argument)
    except DatagenError:
        raise
    except (ValueError, OSError) as exc:
        raise PlannerError(f"planner {spec!r}: {_one_line(exc, named=False)}") from None
    if not isinstance(scorer, ViewScorer):
        raise PlannerError(
            f"planner {spec!r}: plugin {plugin.name!r} ({plugin.value}, {source}) returned a "
            f"{type(scorer).__name__}, not a scorer with view_probabilities(points, view_state)"
        )
    return scorer


def _one_line(exc: BaseException, named: bool = True) -> str:
    """The first line of an exception's message, after its type's name unless ``named`` is False."""
    text = str(exc).strip()
    line = text.splitlines()[0] if text else ""
    return f"{type(exc).__name__}: {line}" if named or not line else line


def make_planner(spec: str) -> Planner:
    """The planner a command-line name stands for; `PlannerError` names the choices otherwise.

    A ``random:match=SPEC`` comes back unbound: `match_planners` binds it to a planner of the same run.
    """
    name, colon, argument = spec.partition(":")
    if colon and not argument:
        raise PlannerError(f"planner {spec!r} names nothing after ':'; choose {planner_help()}")
    base, plus, decoding = name.partition("+")
    if name == "oracle" and not argument:
        return OraclePlanner()
    if name == "all" and not argument:
        return AllPlanner()
    if name == "random" and argument.startswith(MATCH_PREFIX):
        if argument == MATCH_PREFIX:
            raise PlannerError(f"planner {spec!r} names no planner after '='; give random:match=PLANNER")
        return MatchedRandomPlanner(spec, argument.removeprefix(MATCH_PREFIX))
    if name in ("greedy", "random"):
        total = _view_count(spec, argument) if argument else None
        return GreedyPlanner(total) if name == "greedy" else RandomPlanner(total)
    if argument and base not in BUILTIN_PLANNERS:
        if plus and not decoding:
            raise PlannerError(f"planner {spec!r} names no decoding after '+'; give {base}+DECODING:{argument}")
        return ScoredPlanner(spec, plugin_scorer(base, argument, spec), decoding=decoding or None)
    raise PlannerError(f"unknown planner {spec!r}; choose {planner_help()}")


def match_planners(planners: Sequence[Planner]) -> list[Planner]:
    """The planners, in their order, with every ``random:match=SPEC`` bound to the planner SPEC names."""
    return [p.matching(_matched(p, planners)) if isinstance(p, MatchedRandomPlanner) else p for p in planners]


def _matched(planner: MatchedRandomPlanner, planners: Sequence[Planner]) -> Planner:
    """The one planner SPEC names, exactly or as the prefix of a single spec; otherwise one error line naming
    the choices (a matched random matches neither itself nor another matched random: their counts are
    borrowed, not chosen)."""
    choices = {p.name: p for p in planners if not isinstance(p, MatchedRandomPlanner)}
    names = sorted(choices)
    listed = ", ".join(names) if names else "none: add the planner to match"
    found = [n for n in names if n == planner.wanted] or [n for n in names if n.startswith(planner.wanted)]
    if len(found) == 1:
        return choices[found[0]]
    if found:
        problem = f"{planner.wanted!r} is the start of {len(found)} planners; give one in full"
    elif any(isinstance(p, MatchedRandomPlanner) and p.name.startswith(planner.wanted) for p in planners):
        problem = "a matched random cannot match itself or another random:match planner"
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
