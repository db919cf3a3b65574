"""``datagen poco``: train our own POCO weights and evaluate the ``poco`` refiner.

Plain functions; ``datagen/cli/main.py`` builds the ``poco`` group and registers them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from datagen.cli.common import console, print_table, user_errors


def poco_train(
    out: Annotated[Path, typer.Option("--out", help="Run folder: pool.npz, last.pt, best.pt, log.jsonl.")],
    steps: Annotated[int, typer.Option(help="Optimiser steps in all (a resumed run continues to this).")] = 1000,
    preset: Annotated[str, typer.Option(help="Network preset (small_sv, tiny_sv, official, ...).")] = "small_sv",
    seed: Annotated[int, typer.Option(help="Seed of shapes, samples, init and batches.")] = 0,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/last.pt.")] = False,
    init: Annotated[
        Path | None, typer.Option(help="Start from these weights (e.g. the shipped ones), new optimiser.")
    ] = None,
    batch: Annotated[int, typer.Option(help="Samples per step.")] = 4,
    lr: Annotated[float, typer.Option(help="Adam learning rate (constant).")] = 1e-3,
    tasks: Annotated[int, typer.Option(help="Scanned (shape, size, rotation) tasks in the sample pool.")] = 160,
    samples_per_task: Annotated[int, typer.Option(help="Samples (1-3 view cases) cut from each task.")] = 4,
    synth: Annotated[int, typer.Option(help="Synthetic shapes added to the built-ins.")] = 40,
    objects: Annotated[
        Path | None,
        typer.Option("--objects", help="Objects file whose watertight meshes join the training shapes (real scans)."),
    ] = None,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
    checkpoint_every: Annotated[int, typer.Option(help="Steps between validation + checkpoints.")] = 100,
    max_minutes: Annotated[float | None, typer.Option(help="Stop (with a checkpoint) after this wall time.")] = None,
) -> None:
    """Train a POCO network on the built-ins, synthetic shapes and an objects file's watertight meshes, resumable."""
    from datagen.training.poco_train import TrainOptions, train

    with user_errors():
        options = TrainOptions(
            out=out,
            steps=steps,
            preset=preset,
            seed=seed,
            batch=batch,
            lr=lr,
            tasks=tasks,
            samples_per_task=samples_per_task,
            synth=synth,
            objects=objects,
            threads=threads,
            checkpoint_every=checkpoint_every,
            resume=resume,
            init=init,
            max_seconds=None if max_minutes is None else max_minutes * 60.0,
        )
        result = train(options, log=lambda line: console.print(line, markup=False, highlight=False))
        console.print(f"done at step {result['step']}; best {result['best']}", markup=False, highlight=False)


def _parse_views(text: str | None) -> list[int] | None:
    if text is None or not text.strip():
        return None
    try:
        return [int(part) for part in text.replace(" ", "").split(",") if part]
    except ValueError:
        raise typer.BadParameter(f"--views {text!r}: give view indices separated by commas, e.g. 0,4,8") from None


def poco_eval(
    objects: Annotated[Path, typer.Option("--objects", help="Objects file (watertight meshes are evaluated).")],
    weights: Annotated[str, typer.Option(help="Weights file, or 'builtin' (datagen/data/poco_small.pt).")] = "builtin",
    views: Annotated[
        str | None, typer.Option(help="Single views to use, e.g. 0,4,8 (default: every --every-th).")
    ] = None,
    every: Annotated[int, typer.Option(help="Use every N-th view when --views is not given.")] = 4,
    threshold: Annotated[
        float | None, typer.Option(help="p(inside) threshold (default: the config's poco_threshold).")
    ] = None,
    preset: Annotated[str | None, typer.Option(help="Preset (default: the one saved with the weights).")] = None,
    config: Annotated[Path | None, typer.Option("--config", "-c", help="Generation config (TOML).")] = None,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
    poisson: Annotated[bool, typer.Option(help="Also score the poisson refiner (needs Open3D).")] = False,
) -> None:
    """Precision, recall, IoU and hidden-key recall of poco, carve and an oracle on single views."""
    import torch
    from rich.table import Table

    from datagen.config_io import load_config
    from datagen.errors import ConfigError
    from datagen.pipeline.objects.objects_file import ObjectLineError, read_objects_file
    from datagen.pipeline.refine.base import Refiner
    from datagen.pipeline.refine.factory import load_poco_refiner, make_refiner
    from datagen.training.poco_eval import evaluate_object, mean_metrics

    chosen_views = _parse_views(views)
    with user_errors():
        torch.set_num_threads(threads)
        resolved = load_config(config)
        cut = resolved.poco_threshold if threshold is None else threshold
        scored = resolved.model_copy(update={"refiner": "poco", "poco_weights": weights, "poco_threshold": cut})
        path = scored.poco_weights_path()
        if not path.is_file():
            raise ConfigError(f"{path}: weights file not found")
        poco = load_poco_refiner(scored, "cpu", preset)
        refiners: dict[str, Refiner] = {"poco": poco}
        for name in ("carve", "poisson") if poisson else ("carve",):
            refiners[name] = make_refiner(resolved.model_copy(update={"refiner": name}))
        listing = read_objects_file(objects)
        results = []
        for entry in listing.entries:
            if isinstance(entry, ObjectLineError):
                console.print(f"skip line {entry.line}: {entry.message}", markup=False, highlight=False)
                continue
            result = evaluate_object(entry, resolved, refiners, chosen_views, every)
            if result.skipped:
                console.print(f"skip {result.name}: {result.skipped}", markup=False, highlight=False)
            results.append(result)
        table = Table(
            "object",
            "method",
            "prec.",
            "recall",
            "IoU",
            "mIoU",
            "hidden",
            "band",
            "s/view",
            title=f"single views: {poco.model.preset.name}, threshold {cut:g}, {path.name}",
            caption="IoU: occupied class; mIoU: mean of both classes; hidden: recall of hidden P_gt keys; "
            "band: unknown band keys per view",
        )

        def add(name: str, method: str, row: dict[str, float]) -> None:
            table.add_row(
                name,
                method,
                f"{row['precision']:.3f}",
                f"{row['recall']:.3f}",
                f"{row['iou']:.3f}",
                f"{row['miou']:.3f}",
                f"{row['hidden_recall']:.3f}",
                f"{row['band_per_view']:.0f}",
                f"{row['seconds_per_view']:.2f}",
            )

        evaluated = [r for r in results if not r.skipped]
        methods = (*refiners, "oracle")
        for result in evaluated:
            for method in methods:
                add(result.name[:14], method, result.counts[method].metrics())
            table.add_section()
        if evaluated:
            for method in methods:
                add("mean", method, mean_metrics(evaluated, method))
        print_table(table)


def poco_export(
    run: Annotated[Path, typer.Option("--run", help="Training run folder (best.pt, pool.npz).")],
    out: Annotated[Path, typer.Option("--out", help="Weights file to write (fp16 storage).")],
    checkpoint: Annotated[str, typer.Option(help="Checkpoint of the run to export.")] = "best.pt",
    min_hidden_recall: Annotated[
        float, typer.Option(help="Threshold rule: the highest whose validation hidden-key recall reaches this.")
    ] = 0.35,
    seed: Annotated[int, typer.Option(help="The run's seed (selects its validation shapes).")] = 0,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
) -> None:
    """Tune the decision threshold on the run's held-out training shapes and write the weights file."""
    import torch
    from rich.table import Table

    from datagen.pipeline.refine.poco.checkpoint import load_checkpoint
    from datagen.training.poco_checkpoints import export_weights
    from datagen.training.poco_samples import load_pool, split_pool
    from datagen.training.poco_validation import evaluate_pool, threshold_metrics, tune_threshold

    with user_errors():
        torch.set_num_threads(threads)
        source = run / checkpoint
        model = load_checkpoint(source)
        _, val = split_pool(load_pool(run / "pool.npz"), 0.1, seed)
        ev = evaluate_pool(model, val, seed, torch.device("cpu"))
        table = Table(
            "threshold",
            "precision",
            "recall",
            "IoU occ",
            "mIoU",
            "hidden rec.",
            title=f"validation ({len(val)} samples)",
        )
        for t in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9):
            row = threshold_metrics(ev["prob"], ev["label"], ev["is_gt"], t)
            table.add_row(
                *(f"{row[k]:.3f}" for k in ("threshold", "precision", "recall", "iou", "miou", "hidden_recall"))
            )
        print_table(table)
        tuned = tune_threshold(ev["prob"], ev["label"], ev["is_gt"], min_hidden_recall)
        console.print("tuned: " + ", ".join(f"{k} {v:.3f}" for k, v in tuned.items()), markup=False, highlight=False)
        export_weights(source, out, threshold=tuned["threshold"])
        console.print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)", markup=False, highlight=False)
