"""``datagen evaluate``: what view sets achieve on real objects (coverage, views, movement), per planner.

A plain function; `datagen.cli.main` registers it.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import (
    ConfigOption,
    console,
    dataset_options,
    error_console,
    lazy_help,
    plural,
    print_rows,
    progress_bar,
    say,
    user_errors,
)
from datagen.errors import InvalidArgument

EXIT_SOME_FAILED = 1


def _planner_help(load: bool = False) -> str:
    """``--planner``'s help, written from the planner registry (`datagen.evaluate.planners`: every built-in
    kind's usage and every installed plug-in; with ``load``, the names each plug-in offers)."""
    from datagen.evaluate.planners import planner_help

    return (
        f"{planner_help(load=load)}. A plugin's scorer is played one-shot (its views taken at once) or, when it is a "
        "next-best-view scorer, step by step: asked again after every view with the cloud, occupancy grid and "
        "view state observed so far, visiting its best open view, for 10 views in all or --budget-views K, or "
        "until every open view scores 0. Repeat for several."
    )


def _refiner_help() -> str:
    """``--refiner``'s help, from the refiner registry (`schemas.refiners.REFINERS`, plug-ins included)."""
    from schemas.refiners import REFINERS

    *others, last = REFINERS.names()
    return f"{', '.join(others)} or {last} (default: the config's); repeatable."


def evaluate(
    objects: Annotated[Path, typer.Option("--objects", "-o", help="Objects file of the meshes to evaluate on.")],
    planner: Annotated[
        list[str],
        typer.Option(
            "--planner",
            "-p",
            help="The planners: see --help.",
        ),
    ],
    config: ConfigOption = None,
    refiner: Annotated[
        list[str] | None,
        typer.Option("--refiner", "-r", help="The refiners: see --help."),
    ] = None,
    initial_views: Annotated[
        str, typer.Option("--initial-views", help="Initial view ids: 'all', '0,8,16' or '0-3'.")
    ] = "0",
    rotations: Annotated[
        str, typer.Option("--rotations", help="Rotations of each object: 'all', '0,4' or '0-7'.")
    ] = "0",
    budget_views: Annotated[
        int | None,
        typer.Option(
            "--budget-views",
            help="Most views per run, the initial view included; a next-best-view planner plays exactly this many.",
        ),
    ] = None,
    budget_moves: Annotated[float | None, typer.Option("--budget-moves", help="Most movement per run, metres.")] = None,
    per_object: Annotated[bool, typer.Option("--per-object", help="Also print one row per object.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the rows (and every run) as JSON instead.")] = False,
    png: Annotated[
        Path | None,
        typer.Option("--png", help="Coverage against movement budget per planner; one picture per object beside it."),
    ] = None,
    workers: Annotated[int, typer.Option("--workers", "-w", help="Objects evaluated side by side.")] = 0,
    fixed_from: Annotated[
        str | None,
        typer.Option(
            "--fixed-from",
            help=(
                "A training dataset (path or URL) to choose the best fixed view sets from: the fixed planners, "
                "and every planner's lift over the constant plan at equal views."
            ),
        ),
    ] = None,
    tau: Annotated[
        float | None,
        typer.Option("--tau", help="Also report the views each planner needs to see this share (0-1) of the surface."),
    ] = None,
    margins: Annotated[
        str | None,
        typer.Option(
            "--margins",
            help=(
                "Views (the initial one included), e.g. 3,4,6: per object and budget, each planner's margin over "
                "the better of fixed and spread at equal views, the ceiling's (gain) and the share it captures, "
                "and the views it needs to see 95 and 99 %; needs -p gain and -p spread or -p fixed."
            ),
        ),
    ] = None,
) -> None:
    """Simulate the one-shot pipeline on each object and report coverage, views and movement per planner."""
    from datagen.evaluate.episode import Budget
    from datagen.evaluate.margins import MARGIN_COLUMNS, MARGIN_LEGEND, margin_cells, margin_rows, margin_table
    from datagen.evaluate.protocol import PlannerContext
    from datagen.evaluate.report import markdown_table, per_object_rows, summarise, table_cells
    from datagen.evaluate.run import EvaluationSpec, ObjectOutcome, check_planners, evaluate, parse_selection

    with user_errors(fixed_from):
        from datagen.config_io import load_config
        from datagen.evaluate.planner_config import resolve_evaluation_config
        from schemas.config import GenerationConfig

        given = load_config(config) if config is not None else None
        if budget_views is not None and budget_views < 1:
            raise InvalidArgument(f"--budget-views {budget_views}: give at least 1 (the initial view counts)")
        if budget_moves is not None and not budget_moves > 0:
            raise InvalidArgument(f"--budget-moves {budget_moves}: give a positive number of metres")
        if tau is not None and not 0 < tau <= 1:
            raise InvalidArgument(f"--tau {tau}: give a share of the surface in (0, 1]")
        budgets = _margin_budgets(margins, (given or GenerationConfig()).num_views, planner)  # before any loading
        chosen = resolve_evaluation_config(given, planner, refiner)
        resolved = chosen.config
        if chosen.source.startswith("planner") and not as_json:
            say(
                f"imaging as {chosen.source} was trained (config {resolved.config_hash()[:12]}, refiners "
                f"{', '.join(chosen.refiners)}); --config must image alike"
            )
        chosen_views = parse_selection(initial_views, resolved.num_views, "--initial-views")
        chosen_rotations = parse_selection(rotations, resolved.rotations, "--rotations")  # before any work
        fixed = None
        if fixed_from is None:
            check_planners(planner, PlannerContext(resolved))  # a fixed planner: one line naming --fixed-from
        else:
            from datagen.evaluate.fixed_cache import cached_fixed_plans
            from datagen.settings import RunSettings

            cache = RunSettings().home / "cache" / "fixed-plans"
            fixed, remembered = cached_fixed_plans(fixed_from, chosen_views, cache, dataset_options(fixed_from))
            check_planners(planner, PlannerContext(resolved, fixed))
            if not as_json:
                for line in fixed.summary():
                    say(line)
                if remembered:
                    say(f"  (chosen before for these tasks and initial views; kept in {cache})")
        spec = EvaluationSpec(
            planners=tuple(planner),
            refiners=chosen.refiners,
            rotations=chosen_rotations,
            initial_views=chosen_views,
            budget=Budget(views=budget_views, metres=budget_moves),
            pictures=png,
            fixed=fixed,
        )
        started = time.perf_counter()
        with progress_bar(remaining=True) as bar:
            task = bar.add_task("evaluating objects", total=None)

            def finished(outcome: ObjectOutcome) -> None:
                bar.advance(task)
                for failure in outcome.failures:
                    error_console.print(f"error: {failure}", markup=False, highlight=False, soft_wrap=True)

            result = evaluate(objects, resolved, spec, workers=workers or (os.cpu_count() or 1), on_object=finished)
        for failure in result.failures:
            error_console.print(f"error: {failure}", markup=False, highlight=False, soft_wrap=True)
        episodes = result.episodes
        rows = summarise(episodes, tau)
        if png is not None and episodes:
            from datagen.evaluate.figures import draw_budget_curves

            draw_budget_curves(episodes, png)
        if as_json:
            print(
                json.dumps(
                    {
                        "config_hash": resolved.config_hash(),
                        "fixed": None if fixed is None else fixed.as_dict(),
                        "tau": tau,
                        "rows": [row.as_dict() for row in rows],
                        "per_object": [row.as_dict() for row in per_object_rows(episodes, tau)],
                        "runs": [episode.as_dict() for episode in episodes],
                        "margins": [row.as_dict() for row in margin_rows(episodes, budgets)] if budgets else None,
                        "failures": result.all_failures,
                    },
                    indent=1,
                )
            )
        else:
            _show(*table_cells(rows), markdown_table(rows))
            if per_object:
                say("")
                _show(*table_cells(per_object_rows(episodes, tau)), markdown_table(per_object_rows(episodes, tau)))
            if budgets:
                margins_found = margin_rows(episodes, budgets)
                say("")
                for line in MARGIN_LEGEND:
                    say(f"  {line}")
                _show(MARGIN_COLUMNS, margin_cells(margins_found), margin_table(margins_found))
            refine: dict[str, list[float]] = {}
            for outcome in result.outcomes:
                for name, times in outcome.refine_seconds.items():
                    refine.setdefault(name, []).extend(times)
            seconds = ", ".join(f"{name} {sum(v) / len(v):.1f} s" for name, v in refine.items() if v)
            objects_done = sum(1 for o in result.outcomes if o.episodes)
            seconds_taken = time.perf_counter() - started
            took = f"{plural(len(episodes), 'run')} on {plural(objects_done, 'object')} in {seconds_taken:.0f} s"
            say(took + (f"; refining every view of a scene: {seconds}" if seconds else ""))
            if png is not None and episodes:
                say(f"figures: {png} and {sum(len(o.pictures) for o in result.outcomes)} per-object pictures beside it")
        if result.all_failures:
            raise typer.Exit(EXIT_SOME_FAILED)


def _show(header: list[str], cells: list[list[str]], markdown: str) -> None:
    """A table drawn to fit the terminal (ids whole, long cells folded), or as Markdown into a pipe or a
    file, where it pastes into a README."""
    if console.is_terminal:
        print_rows(header, [list(row) for row in cells], whole=["planner"])
    else:
        say(markdown)


EvaluateCommand = lazy_help(planner=lambda: _planner_help(load=True), refiner=lambda: _refiner_help())
"""``datagen evaluate``: its --help lists every planner kind and the names each plug-in offers
(``shipped:nbv``), and the refiners, loading their registries only then."""


def _margin_budgets(text: str | None, num_views: int, planners: list[str]) -> list[int]:
    """``--margins`` as view counts, refused before any work (bad numbers, or no ceiling or floor asked for)."""
    from datagen.evaluate.margins import CEILING, FLOORS, kind_of

    if text is None:
        return []
    try:
        budgets = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        raise InvalidArgument(f"--margins {text!r}: give view counts separated by commas, e.g. 3,4,6") from None
    if not budgets or budgets[0] < 2 or budgets[-1] > num_views:
        raise InvalidArgument(f"--margins {text!r}: give view counts from 2 to {num_views} (the initial view counts)")
    kinds = {kind_of(spec) for spec in planners}
    if CEILING not in kinds or not kinds.intersection(FLOORS):
        raise InvalidArgument(
            "--margins needs the ceiling and a floor among the planners: add -p gain, -p spread and "
            "-p fixed (with --fixed-from)"
        )
    return budgets
