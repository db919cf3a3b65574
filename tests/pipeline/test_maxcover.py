"""Exact maximum coverage (`datagen.pipeline.maxcover`) and the visibility label objectives
(`datagen.pipeline.objectives`, docs/pipeline.md section 7.5), against brute force over every view subset."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from support import storage as fx

from datagen.pipeline.maxcover import CoverageSearch, SearchBudgetExceeded, visibility_masks
from datagen.pipeline.objectives import task_labeller
from datagen.pipeline.setcover import mask_to_views
from schemas.config import GenerationConfig


def brute_best(masks: np.ndarray, weights: np.ndarray, allowed: list[int], budget: int) -> tuple[int, list[int]]:
    """(best weight, every fewest-view set reaching it, in lexicographic order) by trying every subset."""
    best, sets = -1, []
    for size in range(budget + 1):
        for views in itertools.combinations(allowed, size):
            mask = sum(1 << v for v in views)
            value = int(weights[(masks & np.uint64(mask)) != 0].sum())
            if value > best:
                best, sets = value, [mask]
            elif value == best and sets and sets[0].bit_count() == size:
                sets.append(mask)
    return best, sets


def random_instance(seed: int, views: int = 9, elements: int = 40) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    masks = np.zeros(elements, dtype=np.uint64)
    for i in range(elements):
        chosen = rng.choice(views, size=int(rng.integers(1, 4)), replace=False)
        masks[i] = np.uint64(sum(1 << int(v) for v in chosen))
    return masks, rng.integers(1, 4, size=elements).astype(np.int64)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("budget", [1, 2, 3, 4])
def test_best_equals_brute_force_with_every_tie(seed: int, budget: int) -> None:
    masks, weights = random_instance(seed)
    allowed = 0b111111111 & ~(1 << (seed % 9))
    search = CoverageSearch(masks, weights, 9, allowed=allowed)
    answer, ties = search.best(budget, cap=1000)
    value, expected = brute_best(masks, weights, mask_to_views(allowed), budget)
    assert (answer.value, answer.views) == (value, expected[0])
    assert list(ties.sets) == expected and ties.count == len(expected) and ties.exact
    assert ties.support == int(np.bitwise_or.reduce(np.array(expected, dtype=np.uint64)))
    # the walk in lexicographic order agrees, also when the cap cuts the list short
    assert search.answer_for(value, expected[0].bit_count()) == answer
    capped = search.best(budget, cap=1)[1]
    assert capped.sets == (expected[0],) and capped.exact == (len(expected) == 1)
    assert capped.support == ties.support and capped.count == min(len(expected), 2)
    assert search.reaches(value, budget) and not search.reaches(value + 1, budget)


def test_many_ties_are_listed_up_to_the_cap_with_an_exact_support() -> None:
    """Eight views, each seeing one key of its own: every 3-set is as good (56 ties)."""
    masks = np.array([1 << v for v in range(8)], dtype=np.uint64)
    search = CoverageSearch(masks, np.ones(8, dtype=np.int64), 8)
    answer, ties = search.best(3, cap=5)
    assert answer.views == 0b111 and answer.value == 3
    assert not ties.exact and ties.count == 6 and len(ties.sets) == 5 and ties.support == 0xFF
    assert search.tied(3, 3, cap=100).count == 56


def test_a_spent_node_budget_is_an_error_not_a_guess() -> None:
    masks, weights = random_instance(3, views=12, elements=80)
    with pytest.raises(SearchBudgetExceeded, match="without a proof"):
        CoverageSearch(masks, weights, 12, node_budget=3).best(4)


# --- the objectives on the built-ins ---------------------------------------------------------------------


def seen(visible: np.ndarray, views: int) -> int:
    return int(np.count_nonzero((visible & np.uint64(views)) != 0))


def expected_label(key_masks: np.ndarray, case: int, config: GenerationConfig) -> int:
    """The label the objective calls for, by trying every subset of the views outside the case."""
    allowed = [v for v in range(config.num_views) if not case >> v & 1]
    reference = key_masks.size
    if config.label_objective == "max_coverage":
        sizes = range(config.label_budget + 1)
        best = max(seen(key_masks, case | sum(1 << v for v in c)) for c in itertools.combinations(allowed, sizes[-1]))
        target = best
    else:
        target = config.tau_keys(reference)
        sizes = range(len(allowed) + 1)
    for size in sizes:
        hits = [
            (-seen(key_masks, case | mask), mask_to_views(mask), mask)
            for mask in (sum(1 << v for v in c) for c in itertools.combinations(allowed, size))
            if seen(key_masks, case | mask) >= target
        ]
        if hits:
            return min(hits)[2]  # the most seen among the fewest views, then lexicographic
    raise AssertionError("no subset reaches the target")


@pytest.mark.parametrize(
    "changes",
    [
        {"label_objective": "max_coverage", "label_budget": 1},
        {"label_objective": "max_coverage", "label_budget": 2},
        {"label_objective": "partial_cover", "label_tau": 0.8},
        {"label_objective": "partial_cover", "label_tau": 0.9},
    ],
    ids=lambda c: "-".join(str(v) for v in c.values()),
)
def test_visibility_labels_equal_brute_force_on_the_builtins(changes: dict[str, object]) -> None:
    """Every single-view case and every drawn multi-view case of capsule and cone (refiner none)."""
    config = fx.config(**changes)
    checked = 0
    for result in fx.task_results():
        visible = result.sets.visible
        from datagen.pipeline.coverage import view_masks

        key_masks = view_masks(visible)[1]
        labeller = task_labeller(visible, None, config)
        single = [1 << v for v in range(config.num_views)]
        multi = [c for c in result.cases if c.bit_count() > 1][::4]
        for case in single + multi:
            label = labeller.label(case)
            expected = expected_label(key_masks, case, config)
            assert label.label == expected, (result.object_name, mask_to_views(case), changes)
            assert label.status == ("optimal" if expected else "empty")
            assert label.ambiguity is not None and label.label in label.ambiguity.covers
            checked += 1
    assert checked > 64


def test_partial_cover_reaches_tau_with_the_fewest_views() -> None:
    config = fx.config(label_objective="partial_cover", label_tau=0.95)
    result = fx.task_results()[0]
    masks, counts = visibility_masks(result.sets.visible)
    labeller = task_labeller(result.sets.visible, None, config)
    reference = int(counts.sum())
    for view in range(0, 32, 5):
        label = labeller.label(1 << view).label
        covered = int(counts[(masks & np.uint64(label | 1 << view)) != 0].sum())
        assert covered >= config.tau_keys(reference)


def test_every_objective_is_registered_and_an_unknown_one_is_refused_by_name() -> None:
    from schemas.objectives import OBJECTIVES, UnknownObjective

    assert list(OBJECTIVES) == ["cover", "max_coverage", "partial_cover"]
    assert all(callable(objective.load_labeller()) for objective in OBJECTIVES.values())
    config = fx.config().model_copy(update={"label_objective": "best_guess"})  # past the config's own check
    with pytest.raises(UnknownObjective, match="unknown label objective 'best_guess'; choose one of cover"):
        task_labeller((), None, config)
