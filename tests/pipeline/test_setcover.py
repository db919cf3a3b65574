"""Labels (docs/pipeline.md section 7, datagen/pipeline/setcover.py) against an independent brute-force oracle
(tests/support/setcover_oracle.py): the minimum cardinality and the lexicographic tie-break, through every
solving path (the public path, the per-task reduction, the exact branch-and-bound search for the size and
the tie-break, HiGHS's MIP and weighted-MIP fallbacks and the fix-one-view-at-a-time tie-break), under
different HiGHS thread counts, and on every case of two real meshes."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.meshes import REPO_ROOT, SHARED_MESHES, requires_shared_meshes
from support.setcover_oracle import NoCover, oracle_cover, oracle_minimal, oracle_minimum_covers

from datagen.pipeline import setcover
from datagen.pipeline.coverage import coverage_table
from datagen.pipeline.setcover import (
    CoverSearch,
    LabelError,
    TaskCover,
    _fix_lexicographic,
    _solve_lexicographic,
    greedy_cover,
    lexicographic_cover,
    minimal_masks,
    solve_cover,
    solve_min_cover,
)

HYPOTHESIS = {"deadline": None, "database": None, "suppress_health_check": [HealthCheck.too_slow]}
PROOFS = {"forced", "lp-bound", "search", "mip"}


def as_masks(rows: list[int]) -> np.ndarray:
    return np.array(rows, dtype=np.uint64)


def views_of(mask: int) -> list[int]:
    return [v for v in range(mask.bit_length()) if mask >> v & 1]


def candidates_of(rows: np.ndarray) -> list[int]:
    union = int(np.bitwise_or.reduce(rows)) if rows.size else 0
    return views_of(union)


# ---------------------------------------------------------------------------------------------------------
# Random instances: few views, many symmetric rows (so that minimum covers tie), duplicates,
# dominated rows, single-view rows
# ---------------------------------------------------------------------------------------------------------


def rotate(mask: int, shift: int, n: int) -> int:
    shift %= n
    full = (1 << n) - 1
    return ((mask << shift) | (mask >> (n - shift))) & full


@st.composite
def cover_instances(draw: st.DrawFn, min_views: int = 3, max_views: int = 14) -> tuple[int, list[int]]:
    """(n, rows): non-empty view masks over n views."""
    n = draw(st.integers(min_views, max_views), label="n")
    views = st.integers(0, n - 1)
    width = draw(st.integers(2, min(5, n - 1)), label="row width")
    row = st.sets(views, min_size=2, max_size=width).map(lambda vs: sum(1 << v for v in vs))
    base = draw(st.lists(row, min_size=1, max_size=8), label="base rows")
    style = draw(st.sampled_from(["symmetric", "symmetric", "random", "dense"]), label="style")
    rows = list(base)
    if style == "symmetric":
        # closed under a cyclic rotation of the views: minimum covers come in orbits, so ties abound
        step = draw(st.sampled_from([d for d in range(1, n) if n % d == 0] or [1]), label="rotation step")
        rows = [rotate(r, j * step, n) for r in base for j in range(n // step)]
    elif style == "dense":
        full = (1 << n) - 1
        rows += draw(st.lists(st.integers(1, full), max_size=10), label="dense rows")
    else:
        rows += draw(st.lists(row, max_size=20), label="more rows")
    # duplicates, dominated rows (a superset of an existing row) and single-view rows
    rows += draw(st.lists(st.sampled_from(rows), max_size=5), label="duplicates")
    supersets = draw(st.lists(st.tuples(st.sampled_from(rows), st.integers(0, (1 << n) - 1)), max_size=6))
    rows += [r | extra for r, extra in supersets]
    if draw(st.sampled_from([False, False, False, True]), label="add single-view rows"):
        rows += [1 << v for v in draw(st.lists(views, max_size=2), label="single views")]
    order = draw(st.permutations(range(len(rows))), label="row order")
    return n, [rows[i] for i in order]


@st.composite
def cases_of(draw: st.DrawFn) -> tuple[int, list[int], int]:
    """(n, full masks, case S): a task's P_full masks and one input case."""
    n, rows = draw(cover_instances())
    case = draw(st.sets(st.integers(0, n - 1), max_size=n).map(lambda vs: sum(1 << v for v in vs)), label="S")
    return n, rows, case


# ---------------------------------------------------------------------------------------------------------
# 1. The HiGHS label equals the oracle's (size and tie-break); ties are frequent
# ---------------------------------------------------------------------------------------------------------


def test_solve_min_cover_matches_oracle() -> None:
    stats: Counter[str] = Counter()

    @settings(max_examples=350, **HYPOTHESIS)
    @given(cover_instances())
    def check(instance: tuple[int, list[int]]) -> None:
        n, rows = instance
        expected = oracle_cover(rows, count_ties=True)
        solution = solve_cover(as_masks(rows), n)
        assert solution.label == expected.label, (setcover.mask_to_views(solution.label), expected.views)
        assert solution.label.bit_count() == expected.size
        assert solution.proof in PROOFS
        assert solve_min_cover(as_masks(rows), n) == expected.label
        stats["instances"] += 1
        stats["ties"] += expected.ties > 1
        stats[solution.proof] += 1
        stats["single-view rows"] += any(r.bit_count() == 1 for r in rows)

    check()
    print(dict(stats))
    # the tie-break is really exercised: many instances have several minimum covers
    assert stats["ties"] >= 0.4 * stats["instances"], stats
    assert stats["search"] >= 10 and stats["lp-bound"] >= 10 and stats["single-view rows"] >= 20, stats


def test_task_cover_label_matches_oracle() -> None:
    stats: Counter[str] = Counter()

    @settings(max_examples=250, **HYPOTHESIS)
    @given(cases_of())
    def check(instance: tuple[int, list[int], int]) -> None:
        n, full, case = instance
        universe = [m for m in full if m & case == 0]
        result = TaskCover(as_masks(full), n).label(case)
        assert result.rows_before == len(universe)
        assert result.rows_after == len(oracle_minimal(universe))
        assert result.label & case == 0, "the label uses an input view"
        if not universe:
            assert (result.status, result.label, result.objective, result.proof) == ("empty", 0, 0, "none")
            stats["empty"] += 1
            return
        expected = oracle_cover(universe, count_ties=True)
        assert result.status == "optimal"
        assert result.label == expected.label, (result.views, expected.views)
        assert result.objective == expected.size == result.label.bit_count()
        assert result.proof in PROOFS
        assert all(m & result.label for m in universe)
        stats["instances"] += 1
        stats["ties"] += expected.ties > 1

    check()
    print(dict(stats))
    assert stats["ties"] >= 0.3 * stats["instances"], stats
    assert stats["empty"] > 0, stats


def test_hand_made_ties_break_to_the_lexicographically_smallest_tuple() -> None:
    # a 6-cycle: pairs {i, i+1}; the minimum covers are {0,2,4} and {1,3,5}
    cycle = [rotate(0b11, i, 6) for i in range(6)]
    assert setcover.mask_to_views(solve_min_cover(as_masks(cycle), 6)) == (0, 2, 4)
    # covers (0, 5) and (1, 2) tie; lexicographic order compares the first view: (0, 5) < (1, 2)
    rows = [0b000011, 0b100100]
    assert setcover.mask_to_views(solve_min_cover(as_masks(rows), 6)) == (0, 2)
    rows = [0b000011, 0b100000 | 0b000100, 0b100010]
    # {1, 2}, {1, 5} and {0, 5} are covers: the smallest sorted tuple is (0, 5)
    assert setcover.mask_to_views(solve_min_cover(as_masks(rows), 6)) == (0, 5)
    # views forced by single-view rows are part of every cover and of the tie-break
    rows = [0b001000, 0b000110, 0b110000]
    assert setcover.mask_to_views(solve_min_cover(as_masks(rows), 6)) == (1, 3, 4)
    assert solve_cover(as_masks([0b001000, 0b000100, 0b001100]), 6) == setcover.CoverSolution(0b001100, "forced")


def test_no_cover_is_a_label_error() -> None:
    with pytest.raises(setcover.LabelError):
        solve_min_cover(as_masks([0b11, 0]), 2)
    with pytest.raises(NoCover):
        oracle_cover([0b11, 0])


# ---------------------------------------------------------------------------------------------------------
# 2. The reduction (identical and dominated rows) never changes the optimum
# ---------------------------------------------------------------------------------------------------------


@settings(max_examples=200, **HYPOTHESIS)
@given(cover_instances())
def test_reduction_keeps_the_optimum_and_the_tie_break(instance: tuple[int, list[int]]) -> None:
    _, rows = instance
    reduced = minimal_masks(as_masks(rows))
    kept = [int(r) for r in reduced]
    assert reduced.dtype == np.uint64
    assert kept == sorted(set(kept)), "not sorted or not distinct"
    assert not any(a != b and a & b == a for a in kept for b in kept), "a kept row contains another"
    assert set(kept) <= set(rows)
    assert all(any(m & r == m for m in kept) for r in rows), "a raw row contains no kept row"
    assert kept == oracle_minimal(rows)
    raw, small = oracle_cover(rows), oracle_cover(kept)
    assert (raw.size, raw.label) == (small.size, small.label)


def test_minimal_masks_edge_cases() -> None:
    assert minimal_masks(np.empty(0, dtype=np.uint64)).size == 0
    assert minimal_masks([5, 5, 5]).tolist() == [5]
    assert minimal_masks([7, 3, 1, 2]).tolist() == [1, 2]
    top = 1 << 63
    assert minimal_masks(as_masks([top | 1, top, top | 2])).tolist() == [top]


# ---------------------------------------------------------------------------------------------------------
# 3. Every tie-break path agrees with the oracle: the DFS, the weighted MIP, fixing views one by one
# ---------------------------------------------------------------------------------------------------------


@settings(max_examples=150, **HYPOTHESIS)
@given(cover_instances())
def test_every_tie_break_path_matches_oracle(instance: tuple[int, list[int]]) -> None:
    _, rows = instance
    expected = oracle_cover(rows)
    reduced = minimal_masks(as_masks(rows))
    candidates = candidates_of(reduced)
    assert lexicographic_cover(reduced, candidates, expected.size) == expected.label
    assert _solve_lexicographic(reduced, candidates, expected.size, 10.0, 1) == expected.label
    assert _fix_lexicographic(reduced, candidates, expected.size, 10.0, 1) == expected.label
    assert CoverSearch().minimum_size(reduced, candidates, 1, len(candidates)) == expected.size
    if expected.size > 1:
        with pytest.raises(setcover.LabelError, match="is not the minimum"):
            lexicographic_cover(reduced, candidates, expected.size - 1)
        search = CoverSearch()
        assert not search.can_cover(reduced, setcover.views_to_mask(candidates), expected.size - 1)
    greedy = greedy_cover(reduced, candidates)
    assert setcover.covers(greedy, reduced) and greedy.bit_count() >= expected.size


def starve_search(monkeypatch: pytest.MonkeyPatch) -> Counter[str]:
    """Give the exact search no nodes, so that HiGHS answers both the size and the tie-break; count
    the fallbacks' calls."""
    calls: Counter[str] = Counter()
    original_size, original_weighted = setcover._solve, setcover._solve_lexicographic

    def size(*args, **kwargs):
        calls["mip"] += 1
        return original_size(*args, **kwargs)

    def weighted(*args, **kwargs):
        calls["weighted"] += 1
        return original_weighted(*args, **kwargs)

    monkeypatch.setattr(setcover, "SEARCH_NODE_BUDGET", 0)
    monkeypatch.setattr(setcover, "_solve", size)
    monkeypatch.setattr(setcover, "_solve_lexicographic", weighted)
    return calls


def test_public_path_falls_back_to_highs(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = starve_search(monkeypatch)
    proofs: Counter[str] = Counter()

    @settings(max_examples=200, **HYPOTHESIS)
    @given(st.one_of(cases_of(), cover_instances().map(lambda instance: (*instance, 0))))
    def check(instance: tuple[int, list[int], int]) -> None:
        n, full, case = instance
        universe = [m for m in full if m & case == 0]
        result = TaskCover(as_masks(full), n).label(case)
        expected = oracle_cover(universe)
        assert (result.label, result.objective) == (expected.label, expected.size)
        proofs[result.proof] += 1
        assert result.proof != "search"

    check()
    assert calls["weighted"] >= 30 and calls["mip"] >= 10 and proofs["mip"] == calls["mip"], (calls, proofs)


def test_search_budget_is_shared_and_exhaustion_is_none() -> None:
    rows = as_masks([rotate(0b11, i, 8) for i in range(8)])
    candidates = candidates_of(rows)
    assert lexicographic_cover(rows, candidates, 4, node_budget=0) is None
    assert lexicographic_cover(rows, candidates, 4, node_budget=1) is None
    assert lexicographic_cover(rows, candidates, 4) == 0b01010101
    search = CoverSearch(node_budget=3)
    assert search.minimum_size(rows, candidates, 1, 5) is None
    assert search.lexicographic(rows, candidates, 4) is None, "the budget spent by minimum_size is gone"
    assert CoverSearch().minimum_size(rows, candidates, 1, 5) == 4
    assert CoverSearch().minimum_size(rows, candidates, 4, 4) == 4, "upper is returned when no smaller size"


WIDE_TIE = [0x3, 0xFFFFFFFFFFFFFD, 0xA800000000000000, 0xA00000000000000, 0xD00000000000000,
            0xC100000000000000, 0x5100000000000000, 0x1600000000000000]  # fmt: skip
"""64 candidate views, 9 minimum covers of 4 views that differ only in views 56..63, all containing
view 0 (weight 2^63 in the weighted tie-break, whose float64 sum then loses the low weights)."""


def test_wide_instance_oracle_and_exact_paths() -> None:
    expected = oracle_cover(WIDE_TIE, count_ties=True)
    assert expected.views == (0, 56, 57, 59) and expected.ties == 9
    reduced = minimal_masks(as_masks(WIDE_TIE))
    candidates = candidates_of(reduced)
    assert len(candidates) == 64
    assert solve_min_cover(as_masks(WIDE_TIE), 64) == expected.label  # the search's tie-break
    assert _fix_lexicographic(reduced, candidates, 4, 10.0, 1) == expected.label


def test_wide_instance_public_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    expected = oracle_cover(WIDE_TIE)
    starve_search(monkeypatch)
    assert solve_min_cover(as_masks(WIDE_TIE), 64) == expected.label


# ---------------------------------------------------------------------------------------------------------
# 4. Labels do not depend on HiGHS threads or on the run
# ---------------------------------------------------------------------------------------------------------


def mip_heavy_task(seed: int = 7, n: int = 20, rows: int = 70) -> np.ndarray:
    """P_full masks of 3-4 views each over n views: cases need the MIP, not only the LP bound."""
    rng = np.random.default_rng(seed)
    masks = [sum(1 << int(v) for v in rng.choice(n, size=rng.integers(3, 5), replace=False)) for _ in range(rows)]
    return as_masks(masks)


def thread_instances() -> list[tuple[np.ndarray, int, list[int]]]:
    """(full masks, n, cases): random MIP-heavy tasks and a symmetric one."""
    instances = []
    for seed in range(3):
        full = mip_heavy_task(seed)
        rng = np.random.default_rng(100 + seed)
        cases = [0] + [int(sum(1 << int(v) for v in rng.choice(20, size=k, replace=False))) for k in (1, 1, 2, 3, 4)]
        instances.append((full, 20, cases))
    ring = as_masks([rotate(0b1011, i, 12) for i in range(12)])
    instances.append((ring, 12, [0, 1, 0b11, 1 << 5]))
    return instances


THREADS_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from datagen.pipeline import setcover
    from datagen.pipeline.setcover import TaskCover
    data = json.load(open(sys.argv[1]))
    threads = int(sys.argv[2])

    def labels():
        return [[TaskCover(np.array(full, dtype=np.uint64), n).label(c, threads).label for c in cases]
                for full, n, cases in data]

    out = {"plain": labels(), "plain again": labels()}
    setcover.SEARCH_NODE_BUDGET = 0
    out["highs"] = labels()
    print(json.dumps(out))
    """
)


def labels_in_fresh_process(tmp_path: Path, threads: int) -> dict[str, list[list[int]]]:
    """HiGHS fixes its global thread pool at the first run of a process, so each thread count gets
    its own interpreter."""
    data = [([int(m) for m in full], n, cases) for full, n, cases in thread_instances()]
    path = tmp_path / "instances.json"
    path.write_text(json.dumps(data))
    done = subprocess.run(
        [sys.executable, "-c", THREADS_SCRIPT, str(path), str(threads)],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_labels_do_not_depend_on_threads_or_runs(tmp_path: Path) -> None:
    expected = []
    proofs: Counter[str] = Counter()
    for full, n, cases in thread_instances():
        solver = TaskCover(full, n)
        labels = []
        for case in cases:
            universe = [int(m) for m in full if int(m) & case == 0]
            first, again = solver.label(case), solver.label(case)
            assert first.label == again.label == oracle_cover(universe).label
            proofs[first.proof] += 1
            labels.append(first.label)
        expected.append(labels)
    assert proofs["search"] >= 5, proofs
    one = labels_in_fresh_process(tmp_path, 1)
    two = labels_in_fresh_process(tmp_path, 2)
    for run in (one, two):
        assert run["plain"] == run["plain again"] == run["highs"] == expected


def test_threads_can_change_within_one_process() -> None:
    full, n, cases = thread_instances()[0]
    solver = TaskCover(full, n)
    for case in cases:
        assert solver.label(case, threads=1).label == solver.label(case, threads=2).label


# ---------------------------------------------------------------------------------------------------------
# 6. Every case of two real meshes (cow, teapot at 0.15 m, rotation 0, refiner none, targets, alpha 10)
# ---------------------------------------------------------------------------------------------------------


@requires_shared_meshes
@pytest.mark.parametrize("mesh", ["cow.obj", "teapot.obj"])
def test_shared_mesh_labels_match_oracle(mesh: str) -> None:
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, file_object_id
    from datagen.pipeline.refine import make_refiner
    from datagen.pipeline.task import run_task
    from datagen.pipeline.viewspace import build_view_space
    from schemas.config import GenerationConfig

    path = SHARED_MESHES / mesh
    if not path.is_file():
        pytest.skip(f"{path} not found")
    config = GenerationConfig(alpha=10, imaging="targets", refiner="none", label_cover_cap=4096)
    options = ObjectOptions(size=0.15)
    spec = ObjectSpec(source=str(path), name=path.stem, options=options,
                      object_id=file_object_id(path.read_bytes(), options))  # fmt: skip
    result = run_task(prepare_object(spec, config), 0, config, build_view_space(config.view_space),
                      make_refiner(config))  # fmt: skip
    assert result.failures == ()
    coverage = coverage_table(result.sets.refined, config.alpha)
    samples = {s.case: s for s in result.samples}
    assert set(samples) == set(result.cases)
    stats: Counter[str] = Counter()
    for case in result.cases:
        sample = samples[case]
        universe = [int(m) for m in coverage.masks[(coverage.masks & np.uint64(case)) == 0]]
        assert sample.universe_size == len(universe)
        assert sample.cover.rows_after == len(oracle_minimal(universe))
        expected = oracle_cover(universe, count_ties=True)
        assert sample.label == expected.label, (case, sample.cover.views, expected.views)
        assert sample.cover.objective == expected.size
        assert sample.empty_label == (not universe)
        assert sample.cover.ambiguity is not None
        check_ambiguity(sample.cover.ambiguity, sample.label, list(expected.every), config.label_cover_cap)
        stats["ties"] += expected.ties > 1
        stats[sample.cover.proof] += 1
    print(mesh, len(result.cases), dict(stats))


# ---------------------------------------------------------------------------------------------------------
# The tie-break in a view order (`label_tie_break`). The oracle only knows the order by index, so a view
# order is checked by renaming the views: view order[i] becomes view i, the oracle picks the
# lexicographically smallest minimum cover of the renamed rows, and the names are mapped back. The
# "coverage" order is recounted with plain loops over U's keys (most keys first, ties by index).
# ---------------------------------------------------------------------------------------------------------


def renamed(mask: int, order: list[int]) -> int:
    """``mask`` with view order[i] renamed to view i."""
    return sum(1 << i for i, view in enumerate(order) if mask >> view & 1)


def named_back(mask: int, order: list[int]) -> int:
    return sum(1 << view for i, view in enumerate(order) if mask >> i & 1)


def oracle_in_order(rows: list[int], order: list[int]) -> tuple[int, int, int]:
    """(label, size, ties): the lexicographically smallest minimum cover with views compared in ``order``."""
    found = oracle_cover([renamed(r, order) for r in rows], count_ties=True)
    return named_back(found.label, order), found.size, found.ties


def coverage_order(universe: list[int], n: int) -> list[int]:
    """Views by the number of U's keys they cover, most first, ties by index (plain loops)."""
    counts = [sum(1 for key in universe if key >> v & 1) for v in range(n)]
    return sorted(range(n), key=lambda v: (-counts[v], v))


@st.composite
def ordered_instances(draw: st.DrawFn) -> tuple[int, list[int], list[int]]:
    n, rows = draw(cover_instances())
    return n, rows, draw(st.permutations(range(n)), label="view order")


def test_solve_cover_in_a_view_order_matches_the_renamed_oracle() -> None:
    stats: Counter[str] = Counter()

    @settings(max_examples=300, **HYPOTHESIS)
    @given(ordered_instances())
    def check(instance: tuple[int, list[int], list[int]]) -> None:
        n, rows, order = instance
        label, size, ties = oracle_in_order(rows, order)
        solution = solve_cover(as_masks(rows), n, order=order)
        assert solution.label == label, (setcover.mask_to_views(solution.label), setcover.mask_to_views(label))
        assert solution.label.bit_count() == size
        stats["instances"] += 1
        stats["ties"] += ties > 1
        stats["differs from index"] += label != oracle_cover(rows).label

    check()
    assert stats["ties"] >= 0.4 * stats["instances"], stats
    assert stats["differs from index"] >= 0.2 * stats["instances"], stats


def test_task_cover_coverage_tie_break_matches_the_oracle() -> None:
    stats: Counter[str] = Counter()

    @settings(max_examples=250, **HYPOTHESIS)
    @given(cases_of())
    def check(instance: tuple[int, list[int], int]) -> None:
        n, full, case = instance
        universe = [m for m in full if m & case == 0]
        result = TaskCover(as_masks(full), n, tie_break="coverage").label(case)
        if not universe:
            assert (result.status, result.label) == ("empty", 0)
            return
        order = coverage_order(universe, n)
        label, size, _ = oracle_in_order(universe, order)
        assert (result.label, result.objective) == (label, size)
        assert result.label & case == 0
        index_label = TaskCover(as_masks(full), n).label(case).label
        assert index_label.bit_count() == size, "both tie-breaks pick a minimum cover"
        stats["instances"] += 1
        stats["differs from index"] += index_label != label

    check()
    assert stats["differs from index"] >= 0.1 * stats["instances"], stats


def test_every_exact_path_follows_the_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """The search, the weighted MIP and the view-by-view MIP each give the oracle's cover."""

    @settings(max_examples=120, **HYPOTHESIS)
    @given(ordered_instances())
    def check(instance: tuple[int, list[int], list[int]]) -> None:
        _, rows, order = instance
        label, size, _ = oracle_in_order(rows, order)
        reduced = setcover.minimal_masks(as_masks(rows))
        singles = [int(r) for r in reduced if int(r).bit_count() == 1]
        forced = sum(set(singles))
        rest = reduced[(reduced & np.uint64(forced)) == 0]
        if rest.size == 0:
            assert label == forced
            return
        union = int(np.bitwise_or.reduce(rest))
        candidates = [v for v in order if union >> v & 1]
        need = size - forced.bit_count()
        assert forced | CoverSearch().lexicographic(rest, candidates, need) == label
        assert forced | _solve_lexicographic(rest, candidates, need, 10.0, 1) == label
        assert forced | _fix_lexicographic(rest, candidates, need, 10.0, 1) == label

    check()
    calls = starve_search(monkeypatch)

    @settings(max_examples=60, **HYPOTHESIS)
    @given(ordered_instances())
    def through_highs(instance: tuple[int, list[int], list[int]]) -> None:
        n, rows, order = instance
        assert solve_cover(as_masks(rows), n, order=order).label == oracle_in_order(rows, order)[0]

    through_highs()
    assert calls["weighted"] >= 10, calls


def test_coverage_counts_and_order_by_hand() -> None:
    masks = as_masks([0b011, 0b010, 0b110, 0b100])
    assert setcover.coverage_counts(masks, None, 3).tolist() == [1, 3, 2]
    assert setcover.coverage_counts(masks, [5, 1, 1, 2], 3).tolist() == [5, 7, 3]
    assert setcover.view_order([1, 3, 2]) == [1, 2, 0]
    assert setcover.view_order([2, 2, 0, 2]) == [0, 1, 3, 2], "equal coverage goes by index"


def test_coverage_prefers_the_view_that_sees_most() -> None:
    """Keys {0,2} {1,2} {1,2} {0,2} {0,1}: {0,1}, {0,2} and {1,2} all cover them; view 2 holds four keys."""
    full = as_masks([0b101, 0b110, 0b110, 0b101, 0b011])
    assert TaskCover(full, 3).label(0).views == (0, 1)
    assert TaskCover(full, 3, tie_break="coverage").label(0).views == (0, 2)


def test_bad_tie_break_and_order_are_label_errors() -> None:
    with pytest.raises(LabelError, match="unknown tie-break 'fewest'"):
        TaskCover(as_masks([0b11]), 2, tie_break="fewest")  # type: ignore[arg-type]
    with pytest.raises(LabelError, match="each of the 3 views once"):
        solve_cover(as_masks([0b011]), 3, order=[0, 0, 1])


# ---------------------------------------------------------------------------------------------------------
# Every minimum cover (schema version 2): the covers, their count and support against the brute-force
# enumeration of every view set of the minimum size
# ---------------------------------------------------------------------------------------------------------


def check_ambiguity(found: setcover.CoverAmbiguity, label: int, expected: list[int], cap: int) -> None:
    support = 0
    for cover in expected:
        support |= cover
    assert found.support == support
    assert label in found.covers and label in expected
    assert list(found.covers) == sorted(found.covers, key=views_of)
    assert set(found.covers) <= set(expected)
    if len(expected) <= cap:
        assert found.exact and found.count == len(expected)
        assert set(found.covers) == set(expected)
    else:
        assert not found.exact and cap < found.count <= len(expected)
        assert len(found.covers) == cap


@settings(max_examples=200, **HYPOTHESIS)
@given(cover_instances(), st.integers(1, 40))
def test_minimum_covers_match_the_enumeration(instance: tuple[int, list[int]], cap: int) -> None:
    n, rows = instance
    label = solve_min_cover(as_masks(rows), n)
    expected = oracle_minimum_covers(rows)
    check_ambiguity(setcover.minimum_covers(as_masks(rows), n, label, cap), label, expected, cap)


@settings(max_examples=100, **HYPOTHESIS)
@given(cases_of())
def test_task_cover_lists_the_covers_of_each_case(instance: tuple[int, list[int], int]) -> None:
    n, masks, case = instance
    result = TaskCover(as_masks(masks), n, cover_cap=16).label(case)
    universe = [m for m in masks if m & case == 0]
    assert result.ambiguity is not None
    check_ambiguity(result.ambiguity, result.label, oracle_minimum_covers(universe), 16)


def test_minimum_covers_past_the_node_budget_keep_an_exact_support(monkeypatch: pytest.MonkeyPatch) -> None:
    """Six disjoint pairs of views: 2**6 minimum covers. With a node budget too small to list them,
    the count is a lower bound but every view is still found in the support."""
    rows = [0b11 << (2 * i) for i in range(6)]
    label = solve_min_cover(as_masks(rows), 12)
    monkeypatch.setattr(setcover, "ENUMERATION_NODES_PER_COVER", 1)
    found = setcover.minimum_covers(as_masks(rows), 12, label, cap=8)
    assert not found.exact and found.count < 64
    assert found.support == (1 << 12) - 1
    assert label == 0b010101010101 and label in found.covers


def test_minimum_covers_of_an_empty_universe_and_of_forced_views() -> None:
    empty = setcover.minimum_covers(as_masks([]), 8, 0, cap=4)
    assert (empty.covers, empty.count, empty.exact, empty.support) == ((0,), 1, True, 0)
    forced = setcover.minimum_covers(as_masks([0b1, 0b100, 0b101]), 8, 0b101, cap=4)
    assert (forced.covers, forced.count, forced.exact, forced.support) == ((0b101,), 1, True, 0b101)
    with pytest.raises(LabelError, match="does not cover"):
        setcover.minimum_covers(as_masks([0b11, 0b1100]), 8, 0b11, cap=4)
