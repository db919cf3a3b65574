"""studies/planners/real_objects/ensemble_val.py's normalisation: a member's scores become a softmax over
the open views only (taken views weigh nothing, the open views' order is kept), so members whose raw
scores sit at different levels count alike in an ensemble."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def ensemble_val() -> ModuleType:
    return load_study("planners.real_objects.ensemble_val")


def test_open_softmax_is_a_distribution_over_the_open_views(ensemble_val: ModuleType) -> None:
    probabilities = np.array([[0.9, 0.2, 0.6, 0.4], [0.1, 0.1, 0.3, 0.99]], dtype=np.float32)
    state = np.array([[1, 0, 0, 0], [0, 0, 0, 1]], dtype=np.float32)
    soft = ensemble_val.open_softmax(probabilities, state)
    assert np.allclose(soft.sum(axis=1), 1.0)
    assert soft[0, 0] == 0.0 and soft[1, 3] == 0.0  # the taken views, whatever their score
    assert list(np.argsort(-soft[0, 1:])) == list(np.argsort(-probabilities[0, 1:]))
    logits = np.log(np.array([0.2, 0.6, 0.4]) / np.array([0.8, 0.4, 0.6]))  # softmax by hand
    assert np.allclose(soft[0, 1:], np.exp(logits) / np.exp(logits).sum())


def test_a_member_shifted_in_logit_counts_the_same(ensemble_val: ModuleType) -> None:
    """Adding a constant to every logit of a member leaves its softmax, and so its vote, unchanged."""
    rng = np.random.default_rng(3)
    logits = rng.normal(size=(5, 6))
    state = (rng.random((5, 6)) < 0.3).astype(np.float32)
    state[:, 0] = 0.0
    sigmoid = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    plain = ensemble_val.open_softmax(sigmoid(logits).astype(np.float32), state)
    shifted = ensemble_val.open_softmax(sigmoid(logits + 2.0).astype(np.float32), state)
    assert np.allclose(plain, shifted, atol=1e-5)
