"""SCLoss against values computed by hand from the paper's equation 3."""

from __future__ import annotations

import math

import pytest
import torch
from osvp.loss import sc_loss


def probability_loss(p: list[list[float]], g: list[list[float]], lam: float) -> float:
    """Equation 3 term by term in plain Python, from probabilities."""
    per_sample = []
    for ps, gs in zip(p, g, strict=True):
        terms = []
        for pi, gi in zip(ps, gs, strict=True):
            ce = gi * math.log(pi) + (1 - gi) * math.log(1 - pi)
            terms.append((1 - gi) * ce + lam * gi * ce)
        per_sample.append(-sum(terms) / len(terms))
    return sum(per_sample) / len(per_sample)


def test_a_hand_computed_value() -> None:
    # one sample, two views: p = (0.8, 0.4), g = (1, 0), lambda 1.25
    # CE = (ln 0.8, ln 0.6); SCLoss = -(1.25 ln 0.8 + ln 0.6) / 2 = 0.3948775...
    logits = torch.logit(torch.tensor([[0.8, 0.4]], dtype=torch.float64))
    value = float(sc_loss(logits, torch.tensor([[1.0, 0.0]], dtype=torch.float64), 1.25))
    assert value == pytest.approx(-(1.25 * math.log(0.8) + math.log(0.6)) / 2, rel=1e-12)
    assert value == pytest.approx(0.3948775315, rel=1e-9)


@pytest.mark.parametrize("lam", [0.75, 1.0, 1.25, 2.0])
def test_matches_the_equation_on_a_batch(lam: float) -> None:
    p = [[0.9, 0.2, 0.5, 0.7], [0.1, 0.6, 0.3, 0.95]]
    g = [[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]]
    logits = torch.logit(torch.tensor(p, dtype=torch.float64))
    value = float(sc_loss(logits, torch.tensor(g, dtype=torch.float64), lam))
    assert value == pytest.approx(probability_loss(p, g, lam), rel=1e-12)


def test_lambda_one_is_plain_binary_cross_entropy_and_ones_weigh_more_above_one() -> None:
    logits = torch.tensor([[0.3, -1.2, 2.0]])
    labels = torch.tensor([[1.0, 0.0, 1.0]])
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, labels)
    assert float(sc_loss(logits, labels, 1.0)) == pytest.approx(float(bce), rel=1e-6)
    assert float(sc_loss(logits, labels, 2.0)) > float(sc_loss(logits, labels, 1.0))


def test_refuses_mismatched_shapes_and_bad_lambda() -> None:
    with pytest.raises(ValueError, match="one shape"):
        sc_loss(torch.zeros(2, 3), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="positive"):
        sc_loss(torch.zeros(1, 3), torch.zeros(1, 3), 0.0)
