"""The view-state prior on hand-counted frequencies."""

from __future__ import annotations

import numpy as np
import pytest
from osvp.prior import ViewStatePrior


def rows(*bits: str) -> np.ndarray:
    return np.array([[float(b) for b in row] for row in bits], dtype=np.float32)


def test_frequencies_per_state_then_per_size_then_overall() -> None:
    state = rows("100", "100", "010", "110")
    labels = rows("011", "001", "100", "001")
    prior = ViewStatePrior.fit(state, labels, lambda_=1.0)
    q = prior.frequencies(rows("100", "001", "011", "000"))
    assert q[0] == pytest.approx([0.0, 0.5, 1.0])  # state 100 seen twice
    assert q[1] == pytest.approx([1 / 3, 1 / 3, 2 / 3])  # unseen one-view state: the one-view samples
    assert q[2] == pytest.approx([0.0, 0.0, 1.0])  # unseen two-view state: the only two-view sample
    assert q[3] == pytest.approx([0.25, 0.25, 0.75])  # no sample without input views: all of them


@pytest.mark.parametrize(("lambda_", "chosen"), [(1.0, [False, False, True]), (1.25, [False, True, True])])
def test_probabilities_are_the_scloss_minimiser(lambda_: float, chosen: list[bool]) -> None:
    # q = (0, 0.5, 1): with lambda 1 a frequency of one half sits exactly on 0.5 (not chosen)
    prior = ViewStatePrior.fit(rows("100", "100"), rows("001", "011"), lambda_)
    p = prior.probabilities(rows("100"))[0]
    assert p == pytest.approx([0.0, lambda_ * 0.5 / (lambda_ * 0.5 + 0.5), 1.0])
    assert list(p > 0.5) == chosen


def test_bad_shapes() -> None:
    with pytest.raises(ValueError):
        ViewStatePrior.fit(rows("10"), rows("1"), 1.25)
