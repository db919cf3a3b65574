"""Benchmark: what more training data buys, the question every dataset user asks.

    python -m studies.planners.learning_curve --data URL --out DIR [--target mincover] [--decoding size]
        [--objects 10,20,40,80] [--fractions 0.25,0.5] [--also NAME=URL ...] [--steps 12000] [--threads 2]

One `osvp train` run per point, each the same number of gradient steps (`--steps`), each validated on
the same held-out objects of the dataset:

- against the number of training objects: a seeded, nested draw of N of the training objects (the
  10 are among the 20, ...);
- against the number of samples: a seeded, nested fraction of the samples of the largest object count;
- ``--also NAME=URL``: a run on every training object of another dataset of the same config (for
  example the same objects plus seeded variants of them, `datagen objects variants`).

Each point is played on the six unseen watertight meshes (48 runs) beside the best fixed view set of
its training data and random views at its own view count, run by run. Prints a Markdown table
(coverage, views, lift over fixed and over random, held-out F1 against the nearest minimum cover,
training objects and samples) and draws DIR/learning-curve.png.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure

from studies.planners.runs import TrainSpec, held_out, matched, pm, row_of, train, unseen


@dataclass(frozen=True)
class Point:
    name: str
    data: str
    spec: TrainSpec
    kind: str
    """"objects", "samples" or "also": which curve it belongs to."""


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--target", default="mincover")
    parser.add_argument("--decoding", default="size")
    parser.add_argument("--objects", default="10,20,40,80")
    parser.add_argument("--fractions", default="0.25,0.5")
    parser.add_argument("--also", action="append", default=[], metavar="NAME=URL")
    parser.add_argument("--steps", type=int, default=12000)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    counts = [int(v) for v in args.objects.split(",")]
    points = [
        Point(f"objects-{n}", args.data, TrainSpec(f"objects-{n}", args.target, max_objects=n), "objects")
        for n in counts
    ]
    for fraction in [float(v) for v in args.fractions.split(",") if v]:
        name = f"objects-{max(counts)}-samples-{fraction:g}"
        spec = TrainSpec(name, args.target, max_objects=max(counts), sample_fraction=fraction)
        points.append(Point(name, args.data, spec, "samples"))
    for also in args.also:
        name, _, url = also.partition("=")
        points.append(Point(name, url, TrainSpec(name, args.target), "also"))

    rows: list[dict[str, Any]] = []
    for point in points:
        checkpoint = train(point.spec, point.data, args.out, args.steps, args.threads)
        figures = held_out(checkpoint, point.data, [args.decoding], args.threads)
        planner = f"osvp+{args.decoding}:{checkpoint}"
        result = unseen([*matched(planner)], args.out / point.name, "unseen", fixed_from=point.data)
        done = json.loads((args.out / point.name / "done").read_text())
        trained = _trained_on(checkpoint)
        rows.append(
            {
                "point": point.name,
                "kind": point.kind,
                "objects": trained["objects"],
                "samples": trained["samples"],
                "unseen": row_of(result, planner),
                "random": row_of(result, f"random:match={planner}"),
                "fixed": row_of(result, f"fixed:match={planner}"),
                "held_out": figures["decodings"][args.decoding],
                "train_seconds": done["seconds"],
            }
        )
    table = markdown(rows)
    print(table)
    (args.out / "learning-curve.md").write_text(table + "\n")
    (args.out / "learning-curve.json").write_text(json.dumps(rows, indent=1))
    draw(rows, args.out / "learning-curve.png", f"target {args.target}, decoding {args.decoding}")


def _trained_on(checkpoint: Path) -> dict[str, int]:
    """Training objects and samples of a run, from its checkpoint's own record."""
    from osvp.checkpoint import load_checkpoint

    training = load_checkpoint(checkpoint).training
    return {"objects": int(training.get("train_objects", 0)), "samples": int(training["train_samples"])}


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| point | training objects | training samples | coverage % | views | lift over fixed % "
        "| fixed at equal views % | lift over random % | random at equal views % | F1 nearest cover (held out) "
        "| train min |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        unseen_row, held = row["unseen"], row["held_out"]
        lines.append(
            f"| {row['point']} | {row['objects']} | {row['samples']} | {pm(unseen_row, 'coverage')} | "
            f"{pm(unseen_row, 'views')} | {pm(unseen_row, 'lift_fixed')} | {pm(row['fixed'], 'coverage')} | "
            f"{pm(unseen_row, 'lift')} | {pm(row['random'], 'coverage')} | "
            f"{held.get('cover_f1', float('nan')):.3f} | {row['train_seconds'] / 60:.0f} |"
        )
    return "\n".join(lines)


def draw(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Coverage, random at equal views and lift against training objects (left) and training samples
    (right: the object-count points as a line, the sample fractions of the largest count and any
    ``--also`` run as separate markers)."""
    figure = Figure(figsize=(11, 4.2), dpi=100)
    curves = (
        ("coverage", "o-", "planner coverage %"),
        ("fixed", "d--", "fixed, equal views %"),
        ("random", "s--", "random, equal views %"),
        ("lift_fixed", "v-", "lift over fixed %"),
        ("lift", "^-", "lift over random %"),
    )
    for column, kind in enumerate(("objects", "samples")):
        axes = figure.add_subplot(1, 2, column + 1)
        line = sorted((r for r in rows if r["kind"] == "objects"), key=lambda r: r[kind])
        x = [r[kind] for r in line]
        for figure_name, style, label in curves:
            axes.plot(x, [_figure(r, figure_name) for r in line], style, label=label)
        extra = [r for r in rows if r["kind"] != "objects" and (kind == "samples" or r["kind"] == "also")]
        for r in extra:
            axes.plot([r[kind]], [_figure(r, "coverage")], "*", markersize=12, label=f"{r['point']} coverage %")
            axes.plot([r[kind]], [_figure(r, "lift")], "x", markersize=9, label=f"{r['point']} lift %")
        ticks = sorted({r[kind] for r in [*line, *extra]})
        axes.set_xscale("log")
        axes.set_xticks(ticks, [f"{t:,}" for t in ticks], rotation=30 if kind == "samples" else 0, fontsize=8)
        axes.minorticks_off()
        axes.set_xlabel(f"training {kind}")
        axes.grid(True, alpha=0.3)
        axes.legend(fontsize=7)
    figure.suptitle(f"osvp on six unseen meshes against training data ({title})")
    figure.tight_layout()
    figure.savefig(path)


def _figure(row: dict[str, Any], name: str) -> float:
    if name in ("random", "fixed"):
        return float(row[name]["coverage"])
    return float(row["unseen"][name])


if __name__ == "__main__":
    main()
