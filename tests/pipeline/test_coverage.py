"""Filter and coverage (docs/pipeline.md section 5, datagen/pipeline/coverage.py) and how labels use them
(section 7, datagen/pipeline/task.py): P_full and the coverage masks on hand-built P_i, what alpha = 1 and
alpha = n mean for labels, empty universes, and relabelling a task for another alpha from its
stored sets."""

from __future__ import annotations

import itertools
from collections import Counter
from functools import reduce
from pathlib import Path

import numpy as np
import pytest
from support.setcover_oracle import oracle_cover

from datagen.pipeline.coverage import coverage_table, filter_to_ground_truth, view_masks
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.setcover import TaskCover
from datagen.pipeline.task import TaskResult, label_task, run_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig

N = 6


def hand_built_views(private: bool = True) -> list[np.ndarray]:
    """P_i of 6 views as sorted packed int64 keys: overlapping runs, a stride pattern, keys every
    view sees and (``private``) a key only one view sees (negative and huge keys included)."""
    shared = np.arange(-50, -40, dtype=np.int64)
    views = []
    for i in range(N):
        run = np.arange(100 * i, 100 * i + 180, dtype=np.int64)  # overlaps the next view's run
        stride = np.arange(1000 + i, 1200, i + 2, dtype=np.int64)
        own = np.array([2**40 + i] if private else [], dtype=np.int64)
        views.append(np.unique(np.concatenate([shared, run, stride, own])))
    return views


def counts_of(views: list[np.ndarray]) -> Counter[int]:
    return Counter(int(k) for v in views for k in v)


def key_set(keys: np.ndarray) -> set[int]:
    return {int(k) for k in keys}


def all_cases(n: int) -> range:
    return range(1 << n)


def label_of(coverage, case: int):
    return TaskCover(coverage.masks, N).label(case)


def test_view_masks_mark_exactly_the_views_holding_each_key() -> None:
    views = hand_built_views()
    keys, masks = view_masks(views)
    assert keys.dtype == np.int64 and masks.dtype == np.uint64
    assert np.all(np.diff(keys) > 0)
    assert key_set(keys) == set().union(*(key_set(v) for v in views))
    for key, mask in zip(keys.tolist(), masks.tolist(), strict=True):
        assert mask == sum(1 << i for i, v in enumerate(views) if key in key_set(v))
    empty_keys, empty_masks = view_masks([])
    assert empty_keys.size == 0 and empty_masks.size == 0


def test_filter_to_ground_truth_intersects_each_view() -> None:
    views = hand_built_views()
    ground_truth = np.arange(-45, 1100, dtype=np.int64)
    filtered = filter_to_ground_truth(views, ground_truth)
    for view, kept in zip(views, filtered, strict=True):
        assert key_set(kept) == key_set(view) & key_set(ground_truth)
        assert np.all(np.diff(kept) > 0)


@pytest.mark.parametrize("alpha", range(1, N + 1))
def test_p_full_is_the_keys_seen_by_at_least_alpha_views(alpha: int) -> None:
    views = hand_built_views()
    coverage = coverage_table(views, alpha)
    counts = counts_of(views)
    assert coverage.alpha == alpha
    assert key_set(coverage.keys) == {k for k, c in counts.items() if c >= alpha}
    assert len(coverage) == coverage.keys.size == coverage.masks.size
    assert np.all(np.diff(coverage.keys) > 0)
    for i, view in enumerate(views):
        assert key_set(coverage.coverage_set(i)) == key_set(view) & key_set(coverage.keys)  # C_i
    case = 0b100101
    covered = set().union(*(key_set(coverage.coverage_set(i)) for i in (0, 2, 5)))
    assert key_set(coverage.keys[coverage.covered_by(case)]) == covered


def test_alpha_n_keeps_exactly_what_every_view_sees() -> None:
    views = hand_built_views()
    everyone = reduce(set.intersection, (key_set(v) for v in views))
    assert everyone == set(range(-50, -40))
    coverage = coverage_table(views, N)
    assert key_set(coverage.keys) == everyone
    assert set(coverage.masks.tolist()) == {(1 << N) - 1}
    # every single view covers all of P_full: the empty case needs one view (the lowest), any other none
    assert label_of(coverage, 0).views == (0,)
    for case in range(1, 1 << N):
        assert label_of(coverage, case).status == "empty"


def test_alpha_1_case_and_label_cover_everything_any_view_sees() -> None:
    views = hand_built_views()
    coverage = coverage_table(views, 1)
    seen = set().union(*(key_set(v) for v in views))
    assert key_set(coverage.keys) == seen
    solver = TaskCover(coverage.masks, N)
    for case in all_cases(N):
        result = solver.label(case)
        assert result.label & case == 0
        union = case | result.label
        covered = set().union(*(key_set(coverage.coverage_set(i)) for i in range(N) if union >> i & 1))
        assert covered == seen, case
        # every view has a private key here, so every view outside the case is in the label
        assert result.label == ((1 << N) - 1) & ~case


def test_alpha_1_without_private_keys() -> None:
    views = hand_built_views(private=False)
    coverage = coverage_table(views, 1)
    seen = set().union(*(key_set(v) for v in views))
    solver = TaskCover(coverage.masks, N)
    sizes: Counter[int] = Counter()
    for case in all_cases(N):
        result = solver.label(case)
        union = case | result.label
        covered = set().union(*(key_set(coverage.coverage_set(i)) for i in range(N) if union >> i & 1))
        assert covered == seen, case
        sizes[result.objective] += 1
    assert len(sizes) > 2, sizes  # labels of several sizes, not simply "every other view"


@pytest.mark.parametrize("private", [True, False])
def test_labels_cover_the_universe_for_every_alpha_and_case(private: bool) -> None:
    views = hand_built_views(private)
    for alpha in range(1, N + 1):
        coverage = coverage_table(views, alpha)
        solver = TaskCover(coverage.masks, N)
        for case in all_cases(N):
            universe = [int(m) for m in coverage.masks if int(m) & case == 0]
            result = solver.label(case)
            assert result.rows_before == len(universe) == solver.universe_size(case)
            expected = oracle_cover(universe)
            assert (result.label, result.objective) == (expected.label, expected.size)
            universe_keys = key_set(coverage.keys[~coverage.covered_by(case)])
            label_keys = set().union(
                set(), *(key_set(coverage.coverage_set(i)) for i in range(N) if result.label >> i & 1)
            )
            assert universe_keys <= label_keys


def test_empty_universe_gives_an_empty_label() -> None:
    views = hand_built_views()
    coverage = coverage_table(views, 3)
    everything = (1 << N) - 1
    result = label_of(coverage, everything)
    assert (result.status, result.label, result.objective, result.proof) == ("empty", 0, 0, "none")
    assert (result.rows_before, result.rows_after) == (0, 0)
    assert result.views == ()
    # cases short of all views may already cover all of P_full
    covering = [c for c in all_cases(N) if not (coverage.masks & np.uint64(c) == 0).any()]
    assert everything in covering and len(covering) > 1
    for case in covering:
        assert label_of(coverage, case).status == "empty"
    # nothing seen at all
    nothing = coverage_table([np.empty(0, dtype=np.int64)] * N, 1)
    assert len(nothing) == 0 and label_of(nothing, 0).status == "empty"


# ---------------------------------------------------------------------------------------------------------
# run_task and relabel on a built-in (capsule: about 0.3 s per task)
# ---------------------------------------------------------------------------------------------------------


def capsule_task(tmp_path: Path, config: GenerationConfig) -> TaskResult:
    listing = tmp_path / "objects.txt"
    listing.write_text("builtin:capsule\n")
    (spec,) = read_objects_file(listing).objects
    prepared = prepare_object(spec, config)
    return run_task(prepared, 0, config, build_view_space(config.view_space), make_refiner(config))


@pytest.fixture(scope="module")
def capsule_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, TaskResult]:
    folder = tmp_path_factory.mktemp("capsule")
    base = GenerationConfig(refiner="none")
    return {
        "keep": capsule_task(folder, base),
        "drop": capsule_task(folder, base.model_copy(update={"empty_labels": "drop"})),
        "alpha5": capsule_task(folder, base.model_copy(update={"alpha": 5})),
    }


def test_relabel_with_the_task_alpha_reproduces_run_task(capsule_runs: dict[str, TaskResult]) -> None:
    config = GenerationConfig(refiner="none")
    keep = capsule_runs["keep"]
    assert keep.failures == () and keep.dropped_empty == 0
    assert [s.case for s in keep.samples] == list(keep.cases)
    labelled = label_task(keep.sets, keep.cases, config)
    coverage, labels, failures = labelled.coverage, labelled.labels, labelled.failures
    assert failures == []
    assert coverage.alpha == config.alpha
    for sample in keep.samples:
        cover = labels[sample.case]
        assert (cover.label, cover.status, cover.objective, cover.rows_before, cover.rows_after, cover.proof) == (
            sample.cover.label,
            sample.cover.status,
            sample.cover.objective,
            sample.cover.rows_before,
            sample.cover.rows_after,
            sample.cover.proof,
        )
        assert sample.label == cover.label
        assert sample.full_size == len(coverage)
        assert sample.universe_size == cover.rows_before
        assert sample.empty_label == (cover.status == "empty") == (cover.label == 0)
    # the capsule has cases whose inputs already cover P_full at alpha 10
    assert any(s.empty_label for s in keep.samples)
    assert any(not s.empty_label for s in keep.samples)


def test_empty_labels_drop_removes_exactly_the_empty_samples(capsule_runs: dict[str, TaskResult]) -> None:
    keep, drop = capsule_runs["keep"], capsule_runs["drop"]
    assert drop.cases == keep.cases
    empty = [s.sample_id for s in keep.samples if s.empty_label]
    assert drop.dropped_empty == len(empty) > 0
    assert [s.sample_id for s in drop.samples] == [s.sample_id for s in keep.samples if not s.empty_label]
    assert not any(s.empty_label for s in drop.samples)
    kept = {s.sample_id: s for s in keep.samples}
    for sample in drop.samples:
        assert sample.label == kept[sample.sample_id].label
        assert sample.cover.objective == kept[sample.sample_id].cover.objective


def test_relabel_for_another_alpha_matches_a_fresh_run(capsule_runs: dict[str, TaskResult]) -> None:
    keep, fresh = capsule_runs["keep"], capsule_runs["alpha5"]
    assert fresh.cases == keep.cases  # cases come from the visibility sets, not from alpha
    labelled = label_task(keep.sets, keep.cases, GenerationConfig(alpha=5, refiner="none"))
    coverage, labels, failures = labelled.coverage, labelled.labels, labelled.failures
    assert failures == [] and coverage.alpha == 5
    assert {s.case: s.label for s in fresh.samples} == {c: r.label for c, r in labels.items()}
    assert all(s.full_size == len(coverage) for s in fresh.samples)
    assert {s.case: s.label for s in fresh.samples} != {s.case: s.label for s in keep.samples}


def test_alpha_1_labels_complete_every_capsule_case(capsule_runs: dict[str, TaskResult]) -> None:
    keep = capsule_runs["keep"]
    labelled = label_task(keep.sets, keep.cases, GenerationConfig(alpha=1, refiner="none"))
    coverage, labels, failures = labelled.coverage, labelled.labels, labelled.failures
    assert failures == []
    seen = reduce(np.union1d, keep.sets.refined)
    assert np.array_equal(coverage.keys, seen)
    for case, result in labels.items():
        union = np.uint64(case | result.label)
        assert bool(((coverage.masks & union) != 0).all()), case


def test_every_case_pair_of_views(capsule_runs: dict[str, TaskResult]) -> None:
    """Labels of all two-view cases of the capsule at alpha 10 equal the oracle's."""
    keep = capsule_runs["keep"]
    coverage = coverage_table(keep.sets.refined, 10)
    solver = TaskCover(coverage.masks, 32)
    for a, b in itertools.islice(itertools.combinations(range(32), 2), 0, None, 7):
        case = 1 << a | 1 << b
        universe = [int(m) for m in coverage.masks if int(m) & case == 0]
        assert solver.label(case).label == oracle_cover(universe).label
