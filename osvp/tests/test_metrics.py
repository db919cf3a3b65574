"""Precision, recall, F1 and exact-set accuracy on hand-counted cases."""

from __future__ import annotations

import pytest
import torch
from osvp.metrics import SetMetrics


def test_hand_counted_batch() -> None:
    probabilities = torch.tensor([[0.9, 0.6, 0.1, 0.5], [0.2, 0.7, 0.8, 0.4]])
    labels = torch.tensor([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 1.0, 0.0]])
    metrics = SetMetrics()
    metrics.add(probabilities, labels)
    # chosen (p > 0.5): sample 0 = {0, 1}, sample 1 = {1, 2}; labels {0, 3} and {1, 2}
    assert (metrics.true_positives, metrics.false_positives, metrics.false_negatives) == (3, 1, 1)
    assert metrics.precision == pytest.approx(0.75)
    assert metrics.recall == pytest.approx(0.75)
    assert metrics.f1 == pytest.approx(0.75)
    assert metrics.exact_accuracy == pytest.approx(0.5)


def test_exactly_one_half_is_not_chosen_and_batches_accumulate() -> None:
    metrics = SetMetrics()
    metrics.add(torch.tensor([[0.5, 0.51]]), torch.tensor([[1.0, 1.0]]))
    metrics.add(torch.tensor([[0.0, 0.0]]), torch.tensor([[0.0, 0.0]]))
    assert (metrics.true_positives, metrics.false_negatives, metrics.samples) == (1, 1, 2)
    assert metrics.precision == 1.0 and metrics.recall == 0.5 and metrics.f1 == pytest.approx(2 / 3)
    assert metrics.exact_accuracy == 0.5


def test_nothing_predicted_or_nothing_relevant_is_zero_not_nan() -> None:
    metrics = SetMetrics()
    metrics.add(torch.zeros(2, 3), torch.zeros(2, 3))
    assert metrics.as_dict() == {"precision": 0.0, "recall": 0.0, "f1": 0.0, "exact_accuracy": 1.0}
