"""The training record: one CSV row per epoch and the paper's Fig. 5b (validation precision, recall
and F1, and the losses, against the epoch), drawn headless on matplotlib's Agg canvas. Beside the
paper's figures: F1 against the nearest minimum cover and the share of predictions covering U
(threshold 0.5 and the ``size`` decoding), mean predicted views against the labels', the best-view
accuracy of a next-view target, and the same figures on training rows when the run measures its fit."""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # matplotlib is imported only when drawing
    from matplotlib.axes import Axes

DECODED = ("precision", "recall", "f1", "exact_accuracy", "cover_f1", "cover_exact", "covers_u", "views")
"""Validation columns written for each decoding of an epoch (plain: threshold 0.5; ``size_``: size)."""

NEXT_VIEW = ("best_view_accuracy", "gain_mae", "chosen_gain_ratio")
"""Validation columns of a next-view target (`osvp.train.next_view_figures`)."""
FIT = ("f1", "size_cover_f1", "best_view_accuracy")
"""Columns also measured on a fixed draw of training rows (``fit_`` prefix, ``--fit-rows``): the fit curve."""

COLUMNS = (
    "epoch",
    "train_loss",
    "val_loss",
    *DECODED,
    "label_views",
    *(f"size_{key}" for key in DECODED),
    "tuned_threshold",
    "tuned_f1",
    *NEXT_VIEW,
    *(f"fit_{key}" for key in FIT),
    "seconds",
    "train_samples_per_s",
    "loader_samples_per_s",
)
"""metrics.csv's columns; a figure a run does not have (cover ones without covers) is left empty."""


def write_metrics_csv(path: Path, history: Sequence[dict[str, float]]) -> None:
    """Rewrite the whole file from the history (a resumed run continues the same rows)."""
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in history:
            writer.writerow({key: _cell(row.get(key)) for key in COLUMNS})
    os.replace(temporary, path)


def _cell(value: float | None) -> str | float:
    if value is None:
        return ""
    return f"{value:.6g}" if isinstance(value, float) else value


def _plot(axes: Axes, history: Sequence[dict[str, float]], keys: Sequence[tuple[str, str]], title: str) -> None:
    """The columns ``keys`` (column, legend) that the history has, against the epoch."""
    epochs = [row["epoch"] for row in history]
    for key, label in keys:
        if all(key in row for row in history):
            axes.plot(epochs, [row[key] for row in history], marker=".", label=label)
    axes.set_xlabel("epoch")
    axes.set_title(title)
    axes.grid(alpha=0.3)
    if axes.get_legend_handles_labels()[0]:
        axes.legend(loc="best", fontsize="small")


def draw_curves(path: Path, history: Sequence[dict[str, float]], title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(11.0, 8.0), dpi=100)
    FigureCanvasAgg(figure)
    (scores, covers), (views, losses) = figure.subplots(2, 2)
    _plot(scores, history, [("precision", "precision"), ("recall", "recall"), ("f1", "F1")], "validation, p > 0.5")
    scores.set_ylim(0.0, 1.0)
    cover_keys = [
        ("cover_f1", "nearest-cover F1, p > 0.5"),
        ("size_cover_f1", "nearest-cover F1, size"),
        ("covers_u", "covers U, p > 0.5"),
        ("size_covers_u", "covers U, size"),
        ("tuned_f1", "F1 at the tuned threshold"),
        ("fit_size_cover_f1", "nearest-cover F1, size, training rows"),
        ("best_view_accuracy", "best-view accuracy"),
        ("fit_best_view_accuracy", "best-view accuracy, training rows"),
    ]
    _plot(covers, history, cover_keys, "validation against the minimum covers")
    covers.set_ylim(0.0, 1.0)
    _plot(views, history, [("views", "p > 0.5"), ("size_views", "size"), ("label_views", "labels")], "mean views")
    _plot(losses, history, [("train_loss", "train loss"), ("val_loss", "val loss")], "loss")
    figure.suptitle(title)
    figure.tight_layout()
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}.png")
    figure.savefig(temporary)
    os.replace(temporary, path)
