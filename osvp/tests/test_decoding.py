"""Decodings on hand-made probabilities: views of the view state are never chosen, ``size`` rounds the
probability mass (halves up, at least one view unless every one is tiny), names parse or fail in one line."""

from __future__ import annotations

import numpy as np
import pytest
from osvp.decoding import TINY, Decoding, parse_decoding, select_views

P = np.array([0.9, 0.6, 0.4, 0.3, 0.05, 0.55])
TAKEN_5 = np.array([0, 0, 0, 0, 0, 1], dtype=np.float32)
"""View 5 (p = 0.55) is already taken."""


def chosen(probabilities: np.ndarray, state: np.ndarray, decoding: str | Decoding) -> list[int]:
    return np.flatnonzero(select_views(probabilities, state, decoding)).tolist()


@pytest.mark.parametrize(
    ("decoding", "views"),
    [
        ("threshold", [0, 1]),  # 0.9, 0.6 > 0.5; view 5 (0.55) is taken
        ("threshold=0.35", [0, 1, 2]),
        ("threshold=0.6", [0]),  # strictly above, as the paper's rule
        ("topk=2", [0, 1]),
        ("topk=10", [0, 1, 2, 3, 4]),  # every free view, never the taken one
        ("size", [0, 1]),  # free mass 0.9 + 0.6 + 0.4 + 0.3 + 0.05 = 2.25 -> 2 views
        (Decoding("tuned", 0.35), [0, 1, 2]),
    ],
)
def test_each_decoding_by_hand(decoding: str | Decoding, views: list[int]) -> None:
    assert chosen(P, TAKEN_5, decoding) == views


def test_size_counts_only_the_free_views_mass() -> None:
    # view 0 taken: free mass 0.6 + 0.4 + 0.3 + 0.05 + 0.55 = 1.9 -> 2 views, the two most probable free ones
    state = np.array([1, 0, 0, 0, 0, 0], dtype=np.float32)
    assert chosen(P, state, "size") == [1, 5]
    assert chosen(P, state, "threshold") == [1, 5]


@pytest.mark.parametrize(
    ("probabilities", "views"),
    [
        ([0.5, 0.5, 0.5, 0.5, 0.5], [0, 1, 2]),  # 2.5 rounds up to 3 (not to even); ties to the lower index
        ([0.5, 0.5, 0.5, 0.0], [0, 1]),  # 1.5 -> 2
        ([0.7, 0.74, 0.0, 0.0], [1]),  # 1.44 rounds down to 1: the most probable view only
        ([0.2, 0.1, 0.06, 0.0], [0]),  # 0.36 rounds to 0, but at least one view: the most probable
        ([0.04, 0.03, TINY - 1e-6, 0.0], []),  # every probability tiny: nothing is missing
    ],
)
def test_size_rounding(probabilities: list[float], views: list[int]) -> None:
    p = np.array(probabilities)
    assert chosen(p, np.zeros_like(p), "size") == views


def test_size_ignores_a_large_probability_on_a_taken_view() -> None:
    p, state = np.array([0.9, 0.04, 0.01]), np.array([1.0, 0.0, 0.0])
    assert chosen(p, state, "size") == []


def test_a_batch_decodes_row_by_row() -> None:
    rows = np.stack([P, P[::-1]])
    states = np.stack([TAKEN_5, np.zeros(6)])
    for name in ("size", "threshold=0.35", "topk=3"):
        together = select_views(rows, states, name)
        assert together.shape == (2, 6)
        for k in range(2):
            assert np.array_equal(together[k], select_views(rows[k], states[k], name))


def test_names_parse_and_print_back() -> None:
    assert parse_decoding("threshold") == Decoding("threshold", 0.5)
    assert parse_decoding("threshold=0.3").spec == "threshold=0.3"
    assert parse_decoding("topk=4") == Decoding("topk", 4.0) and parse_decoding("topk=4").spec == "topk=4"
    assert parse_decoding("tuned", 0.37) == Decoding("tuned", 0.37) and Decoding("tuned", 0.37).spec == "tuned"
    assert parse_decoding("size").spec == "size" and parse_decoding("threshold").spec == "threshold"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sizes", "unknown decoding 'sizes'; choose threshold, tuned, size, topk"),
        ("threshold=abc", "'abc' is not a number"),
        ("threshold=1.5", "must lie in [0, 1]"),
        ("threshold=nan", "not a finite number"),
        ("topk", "needs its K"),
        ("topk=0", "K must be a whole number >= 1"),
        ("topk=2.5", "K must be a whole number >= 1"),
        ("size=3", "'size' takes no value"),
        ("tuned", "holds no tuned threshold"),
    ],
)
def test_bad_names_are_one_line(text: str, message: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_decoding(text)
    assert message in str(info.value) and "\n" not in str(info.value)
