"""``datagen``: the command line. Builds the typer apps and registers the commands' plain functions.

Each command module (`inputs`, `jobs`, and the `shards` and `poco` groups) imports nothing from
`datagen.cli` but `datagen.cli.common`; this module is the one place that sees them all.
"""

from __future__ import annotations

import typer

from datagen.cli import evaluate, inputs, jobs, poco
from datagen.cli.shards import shards_app

app = typer.Typer(
    help="Exact, reproducible training data for one-shot view planning.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
config_app = typer.Typer(help="Inspect generation configs.", no_args_is_help=True)
objects_app = typer.Typer(help="Built-in shapes, synthetic shapes and objects files.", no_args_is_help=True)
poco_app = typer.Typer(help="Train and evaluate the POCO refiner's network.", no_args_is_help=True)

app.add_typer(config_app, name="config")
app.add_typer(objects_app, name="objects")
app.command("submit")(jobs.submit)
app.command("resume")(jobs.resume)
app.command("status")(jobs.status)
app.command("cancel")(jobs.cancel)
app.command("serve")(jobs.serve)
app.command("evaluate", cls=evaluate.EvaluateCommand)(evaluate.evaluate)
app.add_typer(shards_app, name="shards")
app.add_typer(poco_app, name="poco")

config_app.command("show")(inputs.config_show)
objects_app.command("builtins")(inputs.objects_builtins)
objects_app.command("show")(inputs.objects_show)
objects_app.command("synth")(inputs.objects_synth)
objects_app.command("variants")(inputs.objects_variants)
objects_app.command("scan")(inputs.objects_scan)
objects_app.command("split")(inputs.objects_split)
app.command("scan")(inputs.scan)

poco_app.command("train")(poco.poco_train)
poco_app.command("eval")(poco.poco_eval)
poco_app.command("export")(poco.poco_export)


if __name__ == "__main__":
    app()
