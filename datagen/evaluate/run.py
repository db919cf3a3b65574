"""An evaluation over an objects file: every object x rotation x refiner x initial view x planner.

Each object is imaged once per rotation and refined once per refiner; every planner then answers the
same situations. Planners that read neither the refined input nor the generator's label (greedy, all,
random:K) run once per situation, under the refiner label "-". A ``KIND:match=SPEC`` runs after the
planner it matches (whatever the order given) and takes as many views as that planner chose there;
output keeps the order given. Every planner that looks at the object also gets, run by run, the
coverage of random views, of the best fixed set (``--fixed-from``) and of spread views at its own view
count: its lifts.
Objects run side by side in worker processes (``workers``); the result does not depend on how many
(every random draw has its own stream and torch is held to one thread per worker). An object that
cannot be prepared, or a case the solver cannot label, becomes a failure line and the rest goes on.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

from datagen.errors import ConfigError, DatagenError, InvalidArgument
from datagen.evaluate.baselines import MatchedPlanner, baseline_at_count, chosen_count, is_baseline, match_planners
from datagen.evaluate.episode import Budget, Episode, run_episode
from datagen.evaluate.fixed import FixedPlans
from datagen.evaluate.planners import make_planner
from datagen.evaluate.protocol import Planner, PlannerContext
from datagen.evaluate.scene import Scene, build_scene
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.setcover import LabelError
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig
from schemas.refiners import REFINERS


@dataclass(frozen=True)
class EvaluationSpec:
    """What to evaluate: the planners, refiners, rotations and initial views, and the budgets."""

    planners: tuple[str, ...]
    refiners: tuple[str, ...]
    rotations: tuple[int, ...]
    initial_views: tuple[int, ...]
    budget: Budget = field(default_factory=Budget)
    pictures: Path | None = None
    """Write one picture per object (first rotation and initial view) as ``<stem>-<NN>-<name>.png`` here."""
    fixed: FixedPlans | None = None
    """The best fixed view sets of a training dataset (``--fixed-from``): the ``fixed`` planners and every
    planner's lift over them."""


@dataclass
class ObjectOutcome:
    """Everything one object produced."""

    name: str
    episodes: list[Episode] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    refine_seconds: dict[str, list[float]] = field(default_factory=dict)
    """Per refiner, the time to refine all single views of each scene."""
    pictures: list[Path] = field(default_factory=list)


@dataclass
class Evaluation:
    config: GenerationConfig
    spec: EvaluationSpec
    outcomes: list[ObjectOutcome]
    failures: list[str]
    """Objects-file lines that name no usable object."""

    @property
    def episodes(self) -> list[Episode]:
        return [e for o in self.outcomes for e in o.episodes]

    @property
    def all_failures(self) -> list[str]:
        return [*self.failures, *(f for o in self.outcomes for f in o.failures)]


def parse_selection(text: str, count: int, what: str) -> tuple[int, ...]:
    """``"all"``, ``"3"``, ``"0,8,16"`` or ``"0-7"`` (inclusive) as sorted unique ids below ``count``."""
    if text.strip() == "all":
        return tuple(range(count))
    chosen: set[int] = set()
    for part in text.split(","):
        low, dash, high = part.strip().partition("-")
        try:
            first, last = int(low), int(high if dash else low)
        except ValueError:
            raise InvalidArgument(f"{what} {text!r}: give 'all', ids like 0,8,16 or a range like 0-7") from None
        if not (0 <= first <= last < count):
            raise InvalidArgument(f"{what} {text!r}: ids must lie in 0..{count - 1}")
        chosen.update(range(first, last + 1))
    return tuple(sorted(chosen))


def refiner_config(config: GenerationConfig, refiner: str) -> GenerationConfig:
    """The config with another refiner, validated like a loaded one."""
    if refiner not in REFINERS:
        raise ConfigError(f"unknown refiner {refiner!r}; choose one of {', '.join(REFINERS.names())}")
    return GenerationConfig.model_validate({**config.model_dump(), "refiner": refiner})


def check_planners(names: Sequence[str], context: PlannerContext | None = None) -> list[Planner]:
    """Build every planner once up front, so a bad name, checkpoint or match stops before any imaging."""
    if not names:
        raise InvalidArgument("name at least one --planner")
    return match_planners([make_planner(name, context) for name in names])


def lift_baselines(context: PlannerContext) -> list[MatchedPlanner]:
    """The baselines every run is compared with at its own view count: random, spread, and fixed where
    plans exist."""
    kinds = ("random", "fixed", "spread")
    return [b for b in (baseline_at_count(kind, context) for kind in kinds) if b is not None]


def evaluate(
    objects_file: str | Path,
    config: GenerationConfig,
    spec: EvaluationSpec,
    workers: int = 1,
    on_object: Callable[[ObjectOutcome], None] | None = None,
) -> Evaluation:
    """Run the evaluation; ``on_object`` hears about each object as it finishes (in any order)."""
    check_planners(spec.planners, PlannerContext(config, spec.fixed, spec.budget.views))
    for refiner in spec.refiners:
        refiner_config(config, refiner)
    if not spec.refiners:
        raise InvalidArgument("name at least one refiner")
    listing = read_objects_file(objects_file)
    failures = [str(error) for error in listing.errors]
    objects = listing.objects
    outcomes: list[ObjectOutcome] = []
    jobs = [(index, obj, config, spec) for index, obj in enumerate(objects)]
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            outcomes.append(_evaluate_object(*job))
            if on_object:
                on_object(outcomes[-1])
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context) as pool:
            futures = [pool.submit(_evaluate_object, *job) for job in jobs]
            for future in futures:
                outcomes.append(future.result())
                if on_object:
                    on_object(outcomes[-1])
    return Evaluation(config=config, spec=spec, outcomes=outcomes, failures=failures)


def _evaluate_object(index: int, obj: ObjectSpec, config: GenerationConfig, spec: EvaluationSpec) -> ObjectOutcome:
    outcome = ObjectOutcome(name=obj.name)
    with single_threaded_blas(), fixed_torch_threads():
        try:
            _evaluate_scenes(index, obj, config, spec, outcome)
        except DatagenError as exc:
            outcome.failures.append(f"{obj.name}: {exc}")
    return outcome


def _evaluate_scenes(
    index: int, obj: ObjectSpec, config: GenerationConfig, spec: EvaluationSpec, outcome: ObjectOutcome
) -> None:
    context = PlannerContext(config, spec.fixed, spec.budget.views)
    planners = check_planners(spec.planners, context)  # a plugin's scorer is built once per process
    prepared = prepare_object(obj, config)
    view_space = build_view_space(config.view_space)
    if max(spec.rotations) >= config.rotations:
        raise InvalidArgument(f"rotation {max(spec.rotations)} is outside the config's 0..{config.rotations - 1}")
    lifts = lift_baselines(context)
    configs = [refiner_config(config, name) for name in spec.refiners]
    refiners = [make_refiner(c) for c in configs]
    for rotation in spec.rotations:
        scene = build_scene(prepared, rotation, config, view_space)
        refined = [RefinedScene(scene, r, c) for r, c in zip(refiners, configs, strict=True)]
        for initial in spec.initial_views:
            episodes = _evaluate_situation(scene, refined, initial, planners, spec.budget, outcome, lifts)
            outcome.episodes.extend(episodes)
            if spec.pictures is not None and rotation == spec.rotations[0] and initial == spec.initial_views[0]:
                from datagen.evaluate.figures import draw_object

                path = spec.pictures.parent / f"{spec.pictures.stem}-{index:02d}-{obj.name}.png"
                draw_object(scene, episodes, path)
                outcome.pictures.append(path)
        for r in refined:
            if "views" in r.__dict__:  # refined only when some planner needed it
                outcome.refine_seconds.setdefault(r.refiner.name, []).append(r.refine_seconds)


def _evaluate_situation(
    scene: Scene,
    refined: list[RefinedScene],
    initial: int,
    planners: list[Planner],
    budget: Budget,
    outcome: ObjectOutcome,
    lifts: Sequence[MatchedPlanner] = (),
) -> list[Episode]:
    episodes = []
    for position, refined_scene in enumerate(refined):
        active = [p for p in planners if p.uses_refinement or position == 0]
        episodes += run_situation(Situation(refined_scene, initial), active, budget, outcome.failures, lifts)
    return episodes


def run_situation(
    situation: Situation,
    planners: Sequence[Planner],
    budget: Budget,
    failures: list[str],
    lifts: Sequence[MatchedPlanner] = (),
) -> list[Episode]:
    """Every planner's run on one situation, in the order given; a failed plan adds a line to ``failures``.

    Matched baselines run last (they may match only planners that are not matched baselines), each with
    the view count of its planner's plan here, and are skipped where that plan failed. Each run of a
    planner that looks at the object carries the coverage of each of ``lifts`` (unbound matched
    baselines: random, fixed) at its own view count in this situation, under the same budget."""
    runs: dict[int, Episode] = {}
    for index in sorted(range(len(planners)), key=lambda i: isinstance(planners[i], MatchedPlanner)):
        planner = _situated(planners[index], planners, runs)
        episode = None if planner is None else _attempt(planner, situation, budget, failures)
        if episode is not None:
            runs[index] = episode
    return [_with_lifts(runs[i], planners[i], planners, runs, situation, budget, lifts) for i in sorted(runs)]


def _situated(planner: Planner, planners: Sequence[Planner], runs: dict[int, Episode]) -> Planner | None:
    """The planner to run here: a matched baseline gets its planner's view count (None: that plan failed)."""
    if not isinstance(planner, MatchedPlanner):
        return planner
    matched = next((e for i, e in runs.items() if planners[i].name == planner.matched), None)
    return None if matched is None else planner.taking(chosen_count(matched.planned, matched.initial_view))


def _with_lifts(
    episode: Episode,
    planner: Planner,
    planners: Sequence[Planner],
    runs: dict[int, Episode],
    situation: Situation,
    budget: Budget,
    lifts: Sequence[MatchedPlanner],
) -> Episode:
    """The run with the coverage of random views and of the fixed plan at its own view count: from a
    ``random:match``/``fixed:match`` of this planner in the run, else from ``lifts``."""
    if is_baseline(planner):
        return episode
    found: dict[str, float] = {}
    for index, other in runs.items():
        matched = planners[index]
        if isinstance(matched, MatchedPlanner) and matched.matched == planner.name:
            found.setdefault(matched.kind, other.coverage)
    count = chosen_count(episode.planned, episode.initial_view)
    for baseline in lifts:
        if baseline.kind not in found:
            bound = baseline.matching(planner).taking(count)
            found[baseline.kind] = run_episode(bound, situation, budget, measure=False).coverage
    return replace(
        episode,
        matched_random_coverage=found.get("random"),
        matched_fixed_coverage=found.get("fixed"),
        matched_spread_coverage=found.get("spread"),
    )


def _attempt(planner: Planner, situation: Situation, budget: Budget, failures: list[str]) -> Episode | None:
    try:
        return run_episode(planner, situation, budget)
    except LabelError as exc:
        scene = situation.scene
        failures.append(
            f"{scene.object_name} rotation {scene.rotation} view {situation.initial_view} "
            f"({situation.refined.refiner.name}, {planner.name}): {exc}"
        )
        return None
