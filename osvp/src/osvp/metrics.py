"""How well predicted view sets do: against the stored label, and against every minimum cover.

Against the label: precision, recall and F1 over view bits, and exact-set accuracy. A label is one
arbitrary minimum cover of many, so with a version-2 dataset each prediction is also judged
against the listed minimum cover sharing most views with it (the nearest cover: since minimum
covers all have the label's size, the one of best F1), and by whether it covers the surface still
missing (U) at all. Counts are micro-averaged (summed over every view of every sample), as the
paper's Table I reports one precision and one recall per model. Where a sample's listing is capped
(not ``exact``), the nearest listed cover may be farther than the nearest minimum cover: its F1 is
then a lower bound.

`tune_threshold` picks the ``tuned`` decoding's threshold by these figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

from osvp.covers import CoverBank, bits_to_masks
from osvp.decoding import PAPER_THRESHOLD, Decoding, select_views

THRESHOLD = PAPER_THRESHOLD
TUNING_GRID = tuple(round(0.05 + 0.01 * i, 2) for i in range(91))
"""Thresholds ``tuned`` chooses from: 0.05 to 0.95 in steps of 0.01."""


def _ratio(part: int, whole: int) -> float:
    return part / whole if whole else 0.0


def _f1(true_positives: int, false_positives: int, false_negatives: int) -> float:
    p = _ratio(true_positives, true_positives + false_positives)
    r = _ratio(true_positives, true_positives + false_negatives)
    return 2 * p * r / (p + r) if p + r else 0.0


@dataclass
class SetMetrics:
    """Running counts; add batches, read the ratios."""

    true_positives: int = 0
    false_positives: int = 0
    false_negatives: int = 0
    exact: int = 0
    samples: int = 0
    predicted_views: int = 0
    label_views: int = 0
    judged: int = 0
    """Samples judged against their minimum covers (all of them with a version-2 dataset)."""
    cover_true_positives: int = 0
    cover_false_positives: int = 0
    cover_false_negatives: int = 0
    cover_exact: int = 0
    covering: int = 0
    """Predictions that cover U (with the view state)."""

    def add(self, probabilities: torch.Tensor, labels: torch.Tensor) -> None:
        """The paper's rule (p > 0.5) against the stored labels."""
        chosen = (probabilities > THRESHOLD).detach().cpu().numpy()
        self.add_choices(chosen, labels.detach().cpu().numpy())

    def add_choices(
        self, chosen: npt.ArrayLike, labels: npt.ArrayLike, covers: CoverBank | None = None, judge_universe: bool = True
    ) -> None:
        """Chosen views (S, n) against labels (S, n); with ``covers`` (row k = sample k here) also
        against the nearest minimum cover and, unless ``judge_universe`` is off, U."""
        picked = np.asarray(chosen) > 0.5
        wanted = np.asarray(labels) > 0.5
        self.true_positives += int((picked & wanted).sum())
        self.false_positives += int((picked & ~wanted).sum())
        self.false_negatives += int((~picked & wanted).sum())
        self.exact += int((picked == wanted).all(axis=1).sum())
        self.samples += int(wanted.shape[0])
        self.predicted_views += int(picked.sum())
        self.label_views += int(wanted.sum())
        if covers is None:
            return
        if len(covers) != picked.shape[0]:
            raise ValueError(f"{len(covers)} samples of covers for {picked.shape[0]} predictions")
        for i, views in enumerate(bits_to_masks(picked).tolist()):
            nearest = covers.nearest(i, views)
            shared = (nearest & views).bit_count()
            self.cover_true_positives += shared
            self.cover_false_positives += views.bit_count() - shared
            self.cover_false_negatives += nearest.bit_count() - shared
            self.cover_exact += int(nearest == views)
            if judge_universe:
                self.covering += int(covers.covers_universe(i, views))
        self.judged += picked.shape[0]

    @property
    def precision(self) -> float:
        return _ratio(self.true_positives, self.true_positives + self.false_positives)

    @property
    def recall(self) -> float:
        return _ratio(self.true_positives, self.true_positives + self.false_negatives)

    @property
    def f1(self) -> float:
        return _f1(self.true_positives, self.false_positives, self.false_negatives)

    @property
    def exact_accuracy(self) -> float:
        """Fraction of samples whose chosen set is exactly the label."""
        return _ratio(self.exact, self.samples)

    @property
    def cover_f1(self) -> float:
        """F1 against each prediction's nearest minimum cover."""
        return _f1(self.cover_true_positives, self.cover_false_positives, self.cover_false_negatives)

    def as_dict(self) -> dict[str, float]:
        """The figures; the cover ones only when samples were judged against their covers."""
        figures = {
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
            "exact_accuracy": self.exact_accuracy,
            "views": _ratio(self.predicted_views, self.samples),
            "label_views": _ratio(self.label_views, self.samples),
        }
        if self.judged:
            tp, fp, fn = self.cover_true_positives, self.cover_false_positives, self.cover_false_negatives
            figures |= {
                "cover_precision": _ratio(tp, tp + fp),
                "cover_recall": _ratio(tp, tp + fn),
                "cover_f1": self.cover_f1,
                "cover_exact": _ratio(self.cover_exact, self.judged),
                "covers_u": _ratio(self.covering, self.judged),
            }
        return figures


def decoded_metrics(
    probabilities: npt.ArrayLike,
    view_state: npt.ArrayLike,
    labels: npt.ArrayLike,
    decoding: Decoding | str,
    covers: CoverBank | None = None,
) -> SetMetrics:
    """The figures of ``decoding`` on aligned (S, n) arrays (``covers``: the same S samples)."""
    metrics = SetMetrics()
    metrics.add_choices(select_views(probabilities, view_state, decoding), labels, covers)
    return metrics


def tune_threshold(
    probabilities: npt.ArrayLike,
    view_state: npt.ArrayLike,
    labels: npt.ArrayLike,
    covers: CoverBank | None = None,
) -> tuple[float, float]:
    """(threshold, its F1): the `TUNING_GRID` threshold of best F1 against the nearest minimum cover
    (with ``covers``) or against the label bits (without); ties go to the threshold nearest 0.5."""
    best: tuple[float, float, float] | None = None
    for threshold in TUNING_GRID:
        metrics = SetMetrics()
        chosen = select_views(probabilities, view_state, Decoding("threshold", threshold))
        metrics.add_choices(chosen, labels, covers, judge_universe=False)
        score = metrics.cover_f1 if covers is not None else metrics.f1
        key = (score, -abs(threshold - THRESHOLD), -threshold)
        if best is None or key > best:
            best = key
    assert best is not None
    return -best[2], best[0]
