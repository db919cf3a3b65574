"""The training record: one CSV row per epoch and the paper's Fig. 5b (validation precision, recall
and F1, and the losses, against the epoch), drawn headless on matplotlib's Agg canvas."""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from pathlib import Path

COLUMNS = (
    "epoch",
    "train_loss",
    "val_loss",
    "precision",
    "recall",
    "f1",
    "exact_accuracy",
    "seconds",
    "train_samples_per_s",
    "loader_samples_per_s",
)


def write_metrics_csv(path: Path, history: Sequence[dict[str, float]]) -> None:
    """Rewrite the whole file from the history (a resumed run continues the same rows)."""
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in history:
            writer.writerow({key: (f"{row[key]:.6g}" if isinstance(row[key], float) else row[key]) for key in COLUMNS})
    os.replace(temporary, path)


def draw_curves(path: Path, history: Sequence[dict[str, float]], title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    epochs = [row["epoch"] for row in history]
    figure = Figure(figsize=(10.0, 4.0), dpi=100)
    FigureCanvasAgg(figure)
    scores, losses = figure.subplots(1, 2)
    for key in ("precision", "recall", "f1"):
        scores.plot(epochs, [row[key] for row in history], marker=".", label=key)
    scores.set_xlabel("epoch")
    scores.set_ylim(0.0, 1.0)
    scores.set_title("validation")
    scores.grid(alpha=0.3)
    scores.legend(loc="lower right")
    for key in ("train_loss", "val_loss"):
        losses.plot(epochs, [row[key] for row in history], marker=".", label=key.replace("_", " "))
    losses.set_xlabel("epoch")
    losses.set_title("SCLoss")
    losses.grid(alpha=0.3)
    losses.legend(loc="upper right")
    figure.suptitle(title)
    figure.tight_layout()
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}.png")
    figure.savefig(temporary)
    os.replace(temporary, path)
