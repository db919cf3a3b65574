"""Precision, recall, F1 and exact-set accuracy, nearest-cover F1, the covers-U share and the tuned
threshold on hand-counted cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from osvp.covers import CoverBank, bits_to_masks, masks_to_bits
from osvp.metrics import SetMetrics, decoded_metrics, tune_threshold

from storage import LabelAmbiguity


def ambiguity(covers: list[int], rows: list[int], support: int) -> LabelAmbiguity:
    return LabelAmbiguity(
        covers=np.array(covers, dtype=np.uint64),
        count=len(covers),
        exact=True,
        support=support,
        universe_rows=np.array(rows, dtype=np.uint64),
    )


def bits(*rows: str) -> np.ndarray:
    return np.array([[float(b) for b in row] for row in rows], dtype=np.float32)


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
    figures = {"precision": 0.0, "recall": 0.0, "f1": 0.0, "exact_accuracy": 1.0, "views": 0.0, "label_views": 0.0}
    assert metrics.as_dict() == figures


def test_nearest_cover_f1_and_covers_u_by_hand() -> None:
    # Four views; strings are views 0..3.
    # A: view state {3}, label {0, 1}, covers {0, 1} and {0, 2}, U rows {0} and {1, 2}; predicted {0, 2}
    #    label bits: TP 1 FP 1 FN 1; nearest cover {0, 2}: TP 2 FP 0 FN 0, exact; meets {0} and {1, 2}: covers U
    # B: view state {0}, label {1}, covers {1} and {2}, U rows {1, 2} and {1, 2, 3}; predicted {3}
    #    label bits: TP 0 FP 1 FN 1; both covers share nothing, the first ({1}) is nearest: TP 0 FP 1 FN 1;
    #    misses the row {1, 2}: does not cover U
    # C: view state {1}, empty label (U already seen): covers [{}], no rows; predicted {} -> exact, covers U
    # label bits: TP 1 FP 2 FN 2 -> P = R = F1 = 1/3, exact 1/3
    # nearest cover: TP 2 FP 1 FN 1 -> P = R = F1 = 2/3, exact (A, C) 2/3; covers U (A, C) 2/3; views 3/3 = 1
    covers = CoverBank.build(
        [
            ambiguity([0b0011, 0b0101], [0b0001, 0b0110], 0b0111),
            ambiguity([0b0010, 0b0100], [0b0110, 0b1110], 0b0110),
            ambiguity([0], [], 0),
        ],
        view_states=[0b1000, 0b0001, 0b0010],
        num_views=4,
    )
    metrics = SetMetrics()
    metrics.add_choices(bits("1010", "0001", "0000"), bits("1100", "0100", "0000"), covers)
    assert (metrics.true_positives, metrics.false_positives, metrics.false_negatives) == (1, 2, 2)
    counts = (metrics.cover_true_positives, metrics.cover_false_positives, metrics.cover_false_negatives)
    assert counts == (2, 1, 1)
    figures = metrics.as_dict()
    assert figures["f1"] == pytest.approx(1 / 3) and figures["exact_accuracy"] == pytest.approx(1 / 3)
    assert figures["cover_precision"] == pytest.approx(2 / 3) and figures["cover_recall"] == pytest.approx(2 / 3)
    assert figures["cover_f1"] == pytest.approx(2 / 3) and figures["cover_exact"] == pytest.approx(2 / 3)
    assert figures["covers_u"] == pytest.approx(2 / 3)
    assert figures["views"] == pytest.approx(1.0) and figures["label_views"] == pytest.approx(1.0)
    # The covers' marginals and support: A's covers {0, 1}, {0, 2} -> (1, 0.5, 0.5, 0)
    assert covers.marginals[0] == pytest.approx([1.0, 0.5, 0.5, 0.0])
    assert covers.support[1].tolist() == [0.0, 1.0, 1.0, 0.0]
    # take(): the samples in another order, judged the same
    again = SetMetrics()
    again.add_choices(bits("0000", "1010"), bits("0000", "1100"), covers.take([2, 0]))
    assert (again.cover_true_positives, again.covering, again.judged) == (2, 2, 2)


def test_tuned_threshold_on_a_tiny_validation_set() -> None:
    # Three views, nothing taken. Sample 0: label {0}, covers {0} and {1}, p = (0.3, 0.45, 0.1);
    # sample 1: label {2}, cover {2}, p = (0.05, 0.1, 0.4). Views above t:
    #   0.10 <= t < 0.30: {0, 1} and {2}: nearest covers TP 2 FP 1 FN 0 -> F1 0.8;  label bits: the same, 0.8
    #   0.30 <= t < 0.40: {1} and {2}: nearest covers TP 2 FP 0 FN 0 -> F1 1.0;  label bits: TP 1 FP 1 FN 1, 0.5
    #   0.40 <= t < 0.45: {1} and {}: nearest covers F1 2/3; t >= 0.45: nothing, F1 0
    # Ties go to the threshold nearest 0.5: 0.39 with the covers, 0.29 against the label bits.
    probabilities = np.array([[0.3, 0.45, 0.1], [0.05, 0.1, 0.4]])
    state, labels = np.zeros((2, 3)), bits("100", "001")
    covers = CoverBank.build(
        [ambiguity([0b001, 0b010], [0b011], 0b011), ambiguity([0b100], [0b100], 0b100)], [0, 0], num_views=3
    )
    threshold, score = tune_threshold(probabilities, state, labels, covers)
    assert threshold == pytest.approx(0.39) and score == pytest.approx(1.0)
    threshold, score = tune_threshold(probabilities, state, labels)
    assert threshold == pytest.approx(0.29) and score == pytest.approx(0.8)
    tuned = decoded_metrics(probabilities, state, labels, "threshold=0.39", covers)
    assert tuned.cover_f1 == pytest.approx(1.0) and tuned.as_dict()["covers_u"] == pytest.approx(1.0)


def test_masks_and_bits_round_trip() -> None:
    rows = bits("1010", "0001", "0000")
    assert bits_to_masks(rows).tolist() == [0b0101, 0b1000, 0]
    assert np.array_equal(masks_to_bits(bits_to_masks(rows), 4), rows.astype(bool))
