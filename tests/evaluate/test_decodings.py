"""`osvp+DECODE:FILE`: a scorer's own decodings turn its probabilities into views (`DecodingScorer`); a scorer
without them keeps the 0.5 rule and refuses a decoding; bad decodings are one error line."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from datagen.errors import DatagenError, PlannerError
from datagen.evaluate import planners as planners_module
from datagen.evaluate.planners import make_planner
from datagen.evaluate.scored import ScoredPlanner
from datagen.evaluate.situation import RefinedScene, Situation
from schemas.planning import DecodingScorer

PROBABILITIES = np.linspace(0.0, 0.93, 32)
"""View v scores 0.03 v: views 17.. exceed 0.5, views 11.. exceed 0.3, the top three are 29, 30 and 31."""


class DecodingFake:
    """Decodings ``size`` (the three best views), ``threshold=T`` (above T) and the default (above 0.5)."""

    decodings = ("size", "threshold")

    def __init__(self) -> None:
        self.asked: list[str | None] = []

    def view_probabilities(self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]) -> np.ndarray:
        return PROBABILITIES

    def select_views(
        self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32], decoding: str | None
    ) -> npt.NDArray[np.bool_]:
        self.asked.append(decoding)
        if decoding is None:
            return probabilities > 0.5
        if decoding == "size":
            return probabilities >= np.sort(probabilities)[-3]
        name, _, value = decoding.partition("=")
        if name == "threshold":
            return probabilities > float(value)
        raise ValueError(f"unknown decoding {decoding!r}")


class UnlistedFake(DecodingFake):
    """The same decodings, without listing them: an unknown one is found only when planning."""

    decodings = None  # type: ignore[assignment]


class PlainFake:
    def view_probabilities(self, points: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]) -> np.ndarray:
        return PROBABILITIES


@pytest.fixture
def scorer(monkeypatch: pytest.MonkeyPatch) -> DecodingFake:
    """What ``osvp:FILE`` loads, whatever FILE (the plugin's scorer, `plugin_scorer`)."""
    fake = DecodingFake()
    monkeypatch.setattr(planners_module, "plugin_scorer", lambda name, argument, spec: fake)
    return fake


@pytest.mark.parametrize(
    ("spec_text", "decoding", "views"),
    [
        ("osvp+size:run/best.pt", "size", (29, 30)),  # the initial view 31 is among the three best: dropped
        ("osvp+threshold=0.8:run/best.pt", "threshold=0.8", (27, 28, 29, 30)),
        ("osvp:run/best.pt", None, tuple(range(17, 31))),  # the checkpoint's default
    ],
)
def test_the_decoding_reaches_the_scorer(
    real: RefinedScene, scorer: DecodingFake, spec_text: str, decoding: str | None, views: tuple[int, ...]
) -> None:
    planner = make_planner(spec_text)
    assert isinstance(planner, ScoredPlanner) and planner.name == spec_text and planner.decoding == decoding
    plan = planner.plan(Situation(real, 31))
    assert scorer.asked == [decoding]
    assert plan.views == views
    assert plan.probabilities is not None and np.array_equal(plan.probabilities, PROBABILITIES)


def test_the_fakes_are_what_they_claim() -> None:
    assert isinstance(DecodingFake(), DecodingScorer) and not isinstance(PlainFake(), DecodingScorer)


def test_an_unknown_listed_decoding_stops_at_construction(scorer: DecodingFake) -> None:
    with pytest.raises(PlannerError) as info:
        make_planner("osvp+sizes:run/best.pt")
    assert str(info.value) == "planner 'osvp+sizes:run/best.pt': unknown decoding 'sizes'; choose size, threshold"
    assert scorer.asked == []


def test_an_unknown_unlisted_decoding_is_one_line_when_planning(real: RefinedScene) -> None:
    planner = ScoredPlanner("net+nope", UnlistedFake(), decoding="nope")
    with pytest.raises(PlannerError) as info:
        planner.plan(Situation(real, 0))
    assert str(info.value) == "planner net+nope: unknown decoding 'nope'"


def test_a_scorer_without_decodings_refuses_one(monkeypatch: pytest.MonkeyPatch, real: RefinedScene) -> None:
    with pytest.raises(PlannerError, match=r"this scorer has no decodings; drop '\+size'") as info:
        ScoredPlanner("net", PlainFake(), decoding="size")
    assert "\n" not in str(info.value)
    monkeypatch.setattr(planners_module, "plugin_scorer", lambda name, argument, spec: PlainFake())
    with pytest.raises(PlannerError, match=r"'osvp\+size:model\.pt': this scorer has no decodings"):
        make_planner("osvp+size:model.pt")
    # Without a decoding it keeps the paper's rule.
    assert make_planner("osvp:model.pt").plan(Situation(real, 31)).views == tuple(range(17, 31))


def test_an_empty_decoding_is_refused(scorer: DecodingFake) -> None:
    with pytest.raises(PlannerError, match=r"names no decoding after '\+'"):
        make_planner("osvp+:run/best.pt")


def test_a_selection_of_the_wrong_length_is_refused(real: RefinedScene) -> None:
    class Short(DecodingFake):
        def select_views(
            self, probabilities: npt.NDArray[np.float64], view_state: npt.NDArray[np.float32], decoding: str | None
        ) -> npt.NDArray[np.bool_]:
            return np.ones(31, dtype=bool)

    with pytest.raises(PlannerError, match=r"returned \(31,\) view choices for 32 views"):
        ScoredPlanner("net", Short()).plan(Situation(real, 0))


@pytest.mark.skipif(importlib.util.find_spec("osvp") is None, reason="the osvp package is not installed")
def test_the_checkpoint_is_checked_before_the_decoding(tmp_path: Path) -> None:
    with pytest.raises(DatagenError, match="checkpoint not found"):
        make_planner(f"osvp+size:{tmp_path / 'missing.pt'}")
