"""Precision, recall and F1 over view bits, and exact-set accuracy: how well predicted view sets
match the labels. A view is chosen when its probability exceeds 0.5 (the paper's rule).

Counts are micro-averaged (true/false positives summed over every view of every sample), as the
paper's Table I reports one precision and one recall per model.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

THRESHOLD = 0.5


@dataclass
class SetMetrics:
    """Running counts; add batches, read the ratios."""

    true_positives: int = 0
    false_positives: int = 0
    false_negatives: int = 0
    exact: int = 0
    samples: int = 0

    def add(self, probabilities: torch.Tensor, labels: torch.Tensor) -> None:
        chosen = probabilities > THRESHOLD
        wanted = labels > 0.5
        self.true_positives += int((chosen & wanted).sum())
        self.false_positives += int((chosen & ~wanted).sum())
        self.false_negatives += int((~chosen & wanted).sum())
        self.exact += int((chosen == wanted).all(dim=1).sum())
        self.samples += int(labels.shape[0])

    @property
    def precision(self) -> float:
        predicted = self.true_positives + self.false_positives
        return self.true_positives / predicted if predicted else 0.0

    @property
    def recall(self) -> float:
        relevant = self.true_positives + self.false_negatives
        return self.true_positives / relevant if relevant else 0.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r else 0.0

    @property
    def exact_accuracy(self) -> float:
        """Fraction of samples whose chosen set is exactly the label."""
        return self.exact / self.samples if self.samples else 0.0

    def as_dict(self) -> dict[str, float]:
        return {
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
            "exact_accuracy": self.exact_accuracy,
        }
