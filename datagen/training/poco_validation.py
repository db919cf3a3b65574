"""Measuring a POCO model on pool samples (`poco_samples`) and choosing its decision threshold.

Used for validation during training and by ``datagen poco export``. (The refiner's metrics against
true occupancy on whole objects are in `poco_eval`.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from datagen.pipeline.refine.poco.inputs import predict_probs
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.training.poco_samples import Sample


def evaluate_pool(
    model: PocoModel, samples: Sequence[Sample], seed: int, device: torch.device
) -> dict[str, npt.NDArray[Any]]:
    """Per query (box points excluded): p(inside), label, is_gt, over every query of every sample."""
    model.eval()
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xE7A]))
    generator = torch.Generator().manual_seed(seed)
    probs, labels, gts = [], [], []
    with torch.no_grad():
        for sample in samples:
            keep = ~sample.is_box
            probs.append(
                predict_probs(model, sample.inputs, sample.directions, sample.queries[keep], rng, generator, device)
            )
            labels.append(sample.labels[keep])
            gts.append(sample.is_gt[keep])
    return {"prob": np.concatenate(probs), "label": np.concatenate(labels), "is_gt": np.concatenate(gts)}


def threshold_metrics(
    prob: npt.NDArray[Any], label: npt.NDArray[Any], is_gt: npt.NDArray[Any], t: float
) -> dict[str, float]:
    pred = prob > t
    tp = float((pred & label).sum())
    precision = tp / max(1.0, float(pred.sum()))
    recall = tp / max(1.0, float(label.sum()))
    iou1 = tp / max(1.0, float((pred | label).sum()))
    iou0 = float((~pred & ~label).sum()) / max(1.0, float((~pred | ~label).sum()))
    hidden = float(pred[is_gt].mean()) if is_gt.any() else 0.0
    return {
        "threshold": t,
        "precision": precision,
        "recall": recall,
        "iou": iou1,
        "miou": (iou0 + iou1) / 2,
        "hidden_recall": hidden,
    }


def tune_threshold(
    prob: npt.NDArray[Any], label: npt.NDArray[Any], is_gt: npt.NDArray[Any], min_hidden_recall: float = 0.35
) -> dict[str, float]:
    """The highest threshold (most precise R) that still keeps ``min_hidden_recall`` of the hidden
    P_gt keys; if none does, the threshold of the best mean IoU over both classes."""
    grid = [round(float(t), 3) for t in np.arange(0.05, 0.96, 0.025)]
    rows = [threshold_metrics(prob, label, is_gt, t) for t in grid]
    good = [r for r in rows if r["hidden_recall"] >= min_hidden_recall]
    if good:
        return max(good, key=lambda r: r["threshold"])
    return max(rows, key=lambda r: r["miou"])
