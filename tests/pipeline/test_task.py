"""One task in memory (datagen/pipeline/task.py, docs/pipeline.md sections 4-9): cases, labels, points, metadata,
determinism and relabelling, on the fastest built-in in both imaging modes; the number of cases per
task on real meshes (run with ``-s`` to see it)."""

from __future__ import annotations

import itertools
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from support.meshes import requires_shared_meshes, shared_mesh_paths

from datagen.pipeline.cases import greedy_trajectories, long_tail_cases
from datagen.pipeline.imaging import Observation
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import ObjectSpec
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.task import TaskResult, label_task, run_task, sample_id
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig
from schemas.version import SCHEMA_VERSION

FAST_BUILTIN = "capsule"
MODES = ("targets", "pixels")
VIEW_SPACE = build_view_space(GenerationConfig().view_space)


def read_spec(folder: Path, line: str) -> ObjectSpec:
    path = folder / "objects.txt"
    path.write_text(line + "\n")
    listing = read_objects_file(path)
    assert listing.errors == [], listing.errors
    (spec,) = listing.objects
    return spec


@pytest.fixture(scope="module")
def capsule_spec(tmp_path_factory) -> ObjectSpec:
    return read_spec(tmp_path_factory.mktemp("capsule"), f"builtin:{FAST_BUILTIN}")


def run(spec: ObjectSpec, config: GenerationConfig) -> TaskResult:
    return run_task(prepare_object(spec, config), 0, config, VIEW_SPACE, make_refiner(config))


@pytest.fixture(scope="module", params=MODES)
def task(request, capsule_spec: ObjectSpec) -> tuple[GenerationConfig, TaskResult]:
    config = GenerationConfig(imaging=request.param, refiner="none")
    return config, run(capsule_spec, config)


# ---------------------------------------------------------------------------------------------------------
# Independent recomputation of P_full, C_i and U with plain numpy
# ---------------------------------------------------------------------------------------------------------


def full_keys(refined: tuple[np.ndarray, ...], alpha: int) -> np.ndarray:
    """P_full: keys in at least alpha of the P_i."""
    everything = np.concatenate(refined)
    values, counts = np.unique(everything, return_counts=True)  # P_i are unique, so count = #views
    return values[counts >= alpha]


def coverage_sets(refined: tuple[np.ndarray, ...], p_full: np.ndarray) -> list[np.ndarray]:
    return [np.intersect1d(p, p_full) for p in refined]


def universe(p_full: np.ndarray, cover: list[np.ndarray], case: int) -> np.ndarray:
    """U = P_full minus the union of C_i over the views of the case."""
    views = [v for v in range(len(cover)) if case >> v & 1]
    removed = np.unique(np.concatenate([cover[v] for v in views])) if views else np.empty(0, np.int64)
    return np.setdiff1d(p_full, removed)


def views_of(mask: int) -> list[int]:
    return [v for v in range(mask.bit_length()) if mask >> v & 1]


def covers(u: np.ndarray, cover: list[np.ndarray], label: int) -> bool:
    if u.size == 0:
        return True
    covered = np.zeros(u.size, dtype=bool)
    for v in views_of(label):
        covered |= np.isin(u, cover[v])
    return bool(covered.all())


def row_masks(u: np.ndarray, cover: list[np.ndarray]) -> np.ndarray:
    """For each key of U, the mask of the views whose C_v contains it (distinct masks)."""
    masks = np.zeros(u.size, dtype=np.uint64)
    for v, c in enumerate(cover):
        masks |= np.isin(u, c).astype(np.uint64) << np.uint64(v)
    return np.unique(masks)


def first_lexicographic_cover(rows: np.ndarray, allowed: list[int], size: int) -> int | None:
    """The first sorted tuple of ``size`` allowed views (lexicographic order) covering every row."""
    combos = np.array(list(itertools.combinations(allowed, size)), dtype=np.uint64).reshape(-1, size)
    combo_masks = np.bitwise_or.reduce(np.uint64(1) << combos, axis=1) if size else np.zeros(1, np.uint64)
    ok = ((rows[None, :] & combo_masks[:, None]) != 0).all(axis=1)
    hits = np.flatnonzero(ok)
    return int(combo_masks[hits[0]]) if hits.size else None


# ---------------------------------------------------------------------------------------------------------
# Cases, ids, order
# ---------------------------------------------------------------------------------------------------------


def test_sample_ids_and_order(task) -> None:
    config, result = task
    assert result.failures == ()
    assert result.dropped_empty == 0
    assert len(result.samples) == len(result.cases)
    pattern = re.compile(re.escape(result.task_id) + r"-([0-9a-f]{16})")
    for sample in result.samples:
        match = pattern.fullmatch(sample.sample_id)
        assert match, sample.sample_id
        assert int(match.group(1), 16) == sample.case
        assert sample.sample_id == sample_id(result.task_id, sample.case)
    order = [(s.case.bit_count(), s.case) for s in result.samples]
    assert order == sorted(order) and len(set(order)) == len(order)
    assert [s.case for s in result.samples] == list(result.cases)
    assert sum(1 for s in result.samples if s.case.bit_count() == 1) == config.num_views == 32
    assert {s.case for s in result.samples if s.case.bit_count() == 1} == {1 << v for v in range(32)}
    assert len(result.cases) > 32  # the capsule needs more than one view: there are multi-view cases


def test_cases_are_the_long_tail_draw_from_the_case_stream(task) -> None:
    config, result = task
    rng = stream(config.seed, result.object_id, result.rotation, Purpose.CASES)
    assert list(result.cases) == long_tail_cases(result.sets.visible, rng)
    trajectories = greedy_trajectories(result.sets.visible)
    sizes = Counter(c.bit_count() for c in result.cases)
    for size in range(1, config.num_views + 1):
        assert sizes.get(size, 0) == trajectories.need(size, config.num_views)


def test_labels_are_disjoint_and_cover_u(task) -> None:
    config, result = task
    p_full = full_keys(result.sets.refined, config.alpha)
    cover = coverage_sets(result.sets.refined, p_full)
    assert p_full.size > 0
    checked = 0
    for sample in result.samples:
        assert sample.label & sample.case == 0, sample.sample_id
        u = universe(p_full, cover, sample.case)
        assert sample.full_size == p_full.size
        assert sample.universe_size == u.size
        assert covers(u, cover, sample.label), sample.sample_id
        assert sample.cover.objective == sample.label.bit_count()
        assert sample.empty_label == (u.size == 0)
        if u.size == 0:
            assert sample.label == 0 and sample.cover.status == "empty"
            continue
        assert sample.cover.status == "optimal"
        # Minimum and lexicographically smallest, checked by enumeration for small labels.
        size = sample.label.bit_count()
        if size <= 3:
            rows = row_masks(u, cover)
            allowed = [v for v in range(config.num_views) if not sample.case >> v & 1]
            if size > 1:
                assert first_lexicographic_cover(rows, allowed, size - 1) is None, sample.sample_id
            assert first_lexicographic_cover(rows, allowed, size) == sample.label, sample.sample_id
            checked += 1
    assert checked > 0


def test_observed_points_and_sets(task) -> None:
    config, result = task
    visible = result.sets.visible
    assert len(visible) == config.num_views
    for v_i, p_i in zip(visible, result.sets.refined, strict=True):
        # refiner none: P(O_i) = V_i, and P_i = V_i intersected with P_gt
        assert np.array_equal(p_i, np.intersect1d(v_i, result.sets.ground_truth))
    for sample in result.samples:
        union = np.unique(np.concatenate([visible[v] for v in views_of(sample.case)]))
        assert np.array_equal(sample.observed, union), sample.sample_id
        assert np.array_equal(sample.points, sample.observed)  # refiner none: points == observed
        assert sample.points.dtype == np.int64
    centres = result.samples[0].point_centres(config)
    assert centres.shape == (result.samples[0].points.size, 3) and centres.dtype == np.float32


def test_metadata(task) -> None:
    config, result = task
    assert result.metadata == {
        "refiner": "none",
        "weights_id": "",
        "device": "cpu",
        "seed": config.seed,
        "config_hash": config.config_hash(),
        "schema_version": SCHEMA_VERSION,
    }
    assert result.rotation == 0
    assert result.object_name == FAST_BUILTIN
    assert result.task_id.endswith("-r0")


# ---------------------------------------------------------------------------------------------------------
# Determinism and relabelling
# ---------------------------------------------------------------------------------------------------------


def test_run_twice_is_identical(task, capsule_spec: ObjectSpec) -> None:
    config, first = task
    second = run(capsule_spec, config)
    assert second.cases == first.cases
    assert len(second.samples) == len(first.samples)
    for a, b in zip(first.samples, second.samples, strict=True):
        assert (a.sample_id, a.case, a.label) == (b.sample_id, b.case, b.label)
        assert np.array_equal(a.points, b.points)
        assert np.array_equal(a.observed, b.observed)
    for a, b in zip(first.sets.visible, second.sets.visible, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(first.sets.ground_truth, second.sets.ground_truth)


def test_relabel_with_the_same_alpha_reproduces_labels(task) -> None:
    config, result = task
    labelled = label_task(result.sets, result.cases, config)
    coverage, labels, failures = labelled.coverage, labelled.labels, labelled.failures
    assert failures == []
    assert np.array_equal(coverage.keys, full_keys(result.sets.refined, config.alpha))
    assert {s.case: s.label for s in result.samples} == {c: labels[c].label for c in result.cases}


@pytest.mark.parametrize("alpha", [1, 15, 20])
def test_relabel_for_another_alpha_covers_the_new_u(task, alpha: int) -> None:
    config, result = task
    new = config.model_copy(update={"alpha": alpha})
    labelled = label_task(result.sets, result.cases, new)
    coverage, labels, failures = labelled.coverage, labelled.labels, labelled.failures
    assert failures == []
    p_full = full_keys(result.sets.refined, alpha)
    assert np.array_equal(coverage.keys, p_full)
    cover = coverage_sets(result.sets.refined, p_full)
    assert set(labels) == set(result.cases)
    for case, label in labels.items():
        u = universe(p_full, cover, case)
        assert label.label & case == 0
        assert label.rows_before == u.size
        assert covers(u, cover, label.label)
        assert (label.status == "empty") == (u.size == 0)


def test_empty_labels_drop(capsule_spec: ObjectSpec) -> None:
    # alpha = 32 leaves in P_full only keys that every view saw, so every case covers U: all empty.
    config = GenerationConfig(alpha=32, empty_labels="drop", refiner="none")
    result = run(capsule_spec, config)
    p_full = full_keys(result.sets.refined, 32)
    cover = coverage_sets(result.sets.refined, p_full)
    empty = [c for c in result.cases if universe(p_full, cover, c).size == 0]
    assert result.dropped_empty == len(empty)
    assert len(result.samples) + result.dropped_empty + len(result.failures) == len(result.cases)
    assert all(not s.empty_label for s in result.samples)
    assert {s.case for s in result.samples} == set(result.cases) - set(empty)
    assert len(empty) == len(result.cases) > 0


# ---------------------------------------------------------------------------------------------------------
# Observation.combine (O_S of a case)
# ---------------------------------------------------------------------------------------------------------


def _single(view: int, packed: list[int]) -> Observation:
    count = len(packed)
    return Observation(
        views=(view,),
        origins=np.array([[float(view), 0.0, 1.0]]),
        points=np.full((count, 3), view, dtype=np.float32),
        point_views=np.full(count, view, dtype=np.uint8),
        pixels=np.zeros((count, 2), dtype=np.float32),
        keys=np.array(packed, dtype=np.int64),
    )


def test_observation_combine() -> None:
    a, b, c = _single(5, [3, 9]), _single(1, [1, 3]), _single(7, [])
    combined = Observation.combine([a, b, c])
    assert combined.views == (1, 5, 7)
    assert combined.mask == (1 << 1) | (1 << 5) | (1 << 7)
    assert combined.keys.tolist() == [1, 3, 9]
    assert combined.point_views.tolist() == [1, 1, 5, 5]  # concatenated in view order
    assert np.array_equal(combined.origins[:, 0], [1.0, 5.0, 7.0])
    assert np.array_equal(combined.point_origins()[:, 0], [1.0, 1.0, 5.0, 5.0])
    with pytest.raises(ValueError, match="more than one"):
        Observation.combine([a, _single(5, [2])])


# ---------------------------------------------------------------------------------------------------------
# Real meshes: the number of cases per task (benchmarks/generation/cases.py prints all of them)
# ---------------------------------------------------------------------------------------------------------

SHARED_CHOICE = ("fandisk", "rocker-arm", "teapot")
"""Three of the quicker real meshes (the whole table: ``python -m benchmarks.generation.cases``)."""


@requires_shared_meshes
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("stem", SHARED_CHOICE)
def test_cases_per_task_on_real_meshes(tmp_path: Path, stem: str, mode: str) -> None:
    paths = {p.stem: p for p in shared_mesh_paths()}
    if stem not in paths:
        pytest.skip(f"{stem} not among the shared meshes")
    spec = read_spec(tmp_path, f'"{paths[stem]}" size=0.15')
    config = GenerationConfig(imaging=mode, refiner="none")
    result = run(spec, config)
    sizes = Counter(c.bit_count() for c in result.cases)
    per_size = " ".join(f"{m}:{sizes[m]}" for m in sorted(sizes))
    print(f"\n{stem} {mode}: {len(result.cases)} cases ({per_size})")
    assert 32 < len(result.cases) < 200
    assert result.failures == ()
    assert len(result.samples) == len(result.cases)
