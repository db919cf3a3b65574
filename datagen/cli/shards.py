"""``datagen shards``: the group that inspects, validates, relabels, packs and exports datasets.

Builds `shards_app` and registers the plain functions of `shards_export` (export), `shards_check`
(validate, digest, relabel), `shards_repair` (repair), `shards_pack` (pack), `shards_view` (ls, show,
stats) and `shards_card` (card); `datagen.cli.main` mounts it with
``app.add_typer(shards_app, name="shards")``. A group of its own so that a benchmark or a test can
mount it on its own app.
"""

from __future__ import annotations

import typer

from datagen.cli import shards_card, shards_check, shards_export, shards_pack, shards_repair, shards_view

shards_app = typer.Typer(help="Inspect, validate and export datasets.", no_args_is_help=True)

shards_app.command("export", cls=shards_export.ExportCommand)(shards_export.export)
shards_app.command("validate")(shards_check.validate)
shards_app.command("digest")(shards_check.digest)
shards_app.command("relabel")(shards_check.relabel)
shards_app.command("repair")(shards_repair.repair)
shards_app.command("pack")(shards_pack.pack)
shards_app.command("ls")(shards_view.ls)
shards_app.command("show")(shards_view.show)
shards_app.command("stats")(shards_view.stats)
shards_app.command("card")(shards_card.card)
