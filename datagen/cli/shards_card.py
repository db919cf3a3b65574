"""``datagen shards card``: write a dataset's card (`datagen.inspection.card`) as a README beside the data."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import UrlArgument, dataset_options, say, user_errors

CARD_SIZES = range(1, 11)
"""Fixed view sets the card lists: 1 to 10 new views (the budgets planners are compared at)."""
ROOM_BUDGETS = (2, 3, 4, 6)
"""Views in all at which the card gives the floor and the ceiling on the dataset's own objects."""


def card(
    url: UrlArgument,
    objects: Annotated[
        Path | None, typer.Option("--objects", "-o", help="The objects file the job read: lists mesh sources.")
    ] = None,
    no_fixed: Annotated[bool, typer.Option("--no-fixed", help="Skip the best fixed view sets (a search).")] = False,
    out: Annotated[
        str | None, typer.Option("--out", help="Write the card here ('-': print it) instead of URL/README.md.")
    ] = None,
) -> None:
    """Write the dataset's card: the protocol a paper states (views, rotations, refiner, alpha and
    objective, case sampling), counts, label statistics, the best fixed view sets' coverage, the floor and
    the ceiling at equal views on its own objects, and with --objects the mesh sources and their licence
    notes. `shards export` copies it."""
    from datagen.evaluate.fixed import case_weights, choose_fixed_plans
    from datagen.evaluate.training_room import training_room
    from datagen.inspection.card import FixedRow, card_text, mesh_sources
    from datagen.inspection.stats import dataset_stats
    from datagen.pipeline.objects.objects_file import read_objects_file
    from schemas.dataset import CARD_FILE
    from storage import open_dataset

    with user_errors(url):
        options = dataset_options(url)
        dataset = open_dataset(url, options)
        sources = None
        if objects is not None:  # the file's objects that the dataset holds
            held = set(dataset.counts("object_id"))
            sources = mesh_sources(spec.source for spec in read_objects_file(objects).objects if spec.object_id in held)
        fixed = room = None
        if not no_fixed and len(dataset):
            sizes = range(1, min(CARD_SIZES.stop, dataset.num_views))
            weights = case_weights(url, options)
            plans = choose_fixed_plans(weights, url, (), sizes)
            fixed = [FixedRow(size, p.views, p.mean_coverage, p.exact) for size, p in sorted(plans.by_size.items())]
            budgets = [v for v in ROOM_BUDGETS if v <= dataset.num_views]
            # every initial view's plans (a set holding the initial view is replaced as evaluate replaces it)
            runs = choose_fixed_plans(weights, url, tuple(range(dataset.num_views)), range(1, max(budgets)))
            room = training_room(url, runs, budgets, options)
        refiner_weights = sorted(set(dataset.counts("weights_id")) - {""})
        text = card_text(url, dataset.info, dataset_stats(dataset), fixed, sources, room, refiner_weights)
        if out == "-":
            typer.echo(text, nl=False)
        elif out is not None:
            Path(out).write_text(text)
            say(f"wrote {out}")
        else:
            dataset.location.write_atomic(CARD_FILE, text.encode())
            say(f"wrote {dataset.location.url_of(CARD_FILE)}")
