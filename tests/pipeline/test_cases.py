"""Input cases: MA-SCVP's long-tail sampling (docs/pipeline.md section 6, datagen/pipeline/cases.py).

A hand-derived example pins the greedy trajectories, the gains G[m], the candidates, need(m) and the
seeded draws exactly; properties over random visibility sets check the same rules against a plain
Python reference implementation written from the specification.
"""

from __future__ import annotations

import math
from fractions import Fraction
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from datagen.pipeline.cases import Trajectories, case_sizes, greedy_trajectories, long_tail_cases
from datagen.pipeline.random_streams import Purpose, stream


def keys(*values: int) -> np.ndarray:
    return np.array(sorted(values), dtype=np.int64)


def mask(*views: int) -> int:
    return sum(1 << v for v in set(views))


# ---------------------------------------------------------------------------------------------------------
# The hand-computed example (n = 5 views, keys 0..5)
# ---------------------------------------------------------------------------------------------------------
#
#   V0 = {2}    V1 = {1, 3}    V2 = {0, 2}    V3 = {4, 5}    V4 = {3}        union = {0..5}, 6 keys
#
# "new" lists |V_i \ covered| for every view i; the next view is the argmax, ties to the lowest index.
# A prefix is a candidate while covered < 6; the full-coverage case is not a candidate.
#
# start 0: covered {2} (1)              -> candidate {0}          = 0b00001 =  1     G[0] += 1
#          new: V1 2, V2 1, V3 2, V4 1    tie V1/V3 -> V1 (+2)
#          covered {1,2,3} (3)           -> candidate {0,1}        = 0b00011 =  3     G[1] += 2
#          new: V2 1, V3 2, V4 0          -> V3 (+2)
#          covered {1,2,3,4,5} (5)       -> candidate {0,1,3}      = 0b01011 = 11     G[2] += 2
#          new: V2 1, V4 0                -> V2 (+1): full, {0,1,2,3} not a candidate   G[3] += 1
# start 1: covered {1,3} (2)             -> candidate {1}          =  2               G[0] += 2
#          new: V0 1, V2 2, V3 2, V4 0    tie V2/V3 -> V2 (+2)
#          covered {0,1,2,3} (4)         -> candidate {1,2}        = 0b00110 =  6     G[1] += 2
#          new: V3 2                      -> V3 (+2): full                              G[2] += 2
# start 2: covered {0,2} (2)             -> candidate {2}          =  4               G[0] += 2
#          new: V0 0, V1 2, V3 2, V4 1    tie V1/V3 -> V1 (+2)
#          covered {0,1,2,3} (4)         -> candidate {1,2}        =  6 (DUPLICATE)   G[1] += 2
#          new: V3 2                      -> V3 (+2): full                              G[2] += 2
# start 3: covered {4,5} (2)             -> candidate {3}          =  8               G[0] += 2
#          new: V0 1, V1 2, V2 2, V4 1    tie V1/V2 -> V1 (+2)
#          covered {1,3,4,5} (4)         -> candidate {1,3}        = 0b01010 = 10     G[1] += 2
#          new: V0 1, V2 2, V4 0          -> V2 (+2): full                              G[2] += 2
# start 4: covered {3} (1)               -> candidate {4}          = 16               G[0] += 1
#          new: V0 1, V1 1, V2 2, V3 2    tie V2/V3 -> V2 (+2)
#          covered {0,2,3} (3)           -> candidate {2,4}        = 0b10100 = 20     G[1] += 2
#          new: V0 0, V1 1, V3 2          -> V3 (+2)
#          covered {0,2,3,4,5} (5)       -> candidate {2,3,4}      = 0b11100 = 28     G[2] += 2
#          new: V1 1                      -> V1 (+1): full                              G[3] += 1
#
# Trajectory lengths 4, 3, 3, 3, 4 views. Totals:
#   G = [1+2+2+2+1, 2+2+2+2+2, 2+2+2+2+2, 1+0+0+0+1, 0, 0] = [8, 10, 10, 2, 0, 0]
#   (each trajectory's gains sum to |union| = 6, so sum(G) = 5 * 6 = 30)
# Distinct candidates, sorted: size 1 [1, 2, 4, 8, 16]; size 2 [3, 6, 10, 20]; size 3 [11, 28].
# need(1) = n = 5
# need(2) = ceil(5 * 10 / 10) = 5, capped by 4 distinct size-2 candidates -> 4 (every one is drawn)
# need(3) = ceil(5 * 2 / 10)  = 1 (of 2 candidates: a real draw)
# need(4) = ceil(5 * 0 / 10)  = 0, need(5) = 0

HAND_VISIBLE = [keys(2), keys(1, 3), keys(0, 2), keys(4, 5), keys(3)]
HAND_N = 5
HAND_GAINS = [8, 10, 10, 2, 0, 0]
HAND_CANDIDATES = {1: [1, 2, 4, 8, 16], 2: [3, 6, 10, 20], 3: [11, 28]}
HAND_NEED = {1: 5, 2: 4, 3: 1, 4: 0, 5: 0}
HAND_NEED_UNCAPPED = {1: 5, 2: 5, 3: 1, 4: 0, 5: 0}


def test_hand_example_trajectories() -> None:
    trajectories = greedy_trajectories(HAND_VISIBLE)
    assert trajectories.gains.tolist() == HAND_GAINS
    assert trajectories.candidates == HAND_CANDIDATES
    for size in range(1, HAND_N + 1):
        assert trajectories.need(size, HAND_N) == HAND_NEED[size], size
        assert trajectories.need(size, HAND_N, capped=False) == HAND_NEED_UNCAPPED[size], size


def test_hand_example_masks_decode_as_derived() -> None:
    assert HAND_CANDIDATES[2] == sorted([mask(0, 1), mask(1, 2), mask(1, 3), mask(2, 4)])
    assert HAND_CANDIDATES[3] == sorted([mask(0, 1, 3), mask(2, 3, 4)])


def expected_draws(candidates: dict[int, list[int]], need: dict[int, int], n: int, rng) -> list[int]:
    """The documented procedure, spelled out: singletons, then for each size m >= 2 ascending with
    need > 0, ``rng.choice(len(pool), size=need, replace=False)`` over the sorted pool; the cases
    finally ordered by (size, mask)."""
    cases = [1 << v for v in range(n)]
    for size in range(2, n + 1):
        if need.get(size, 0) == 0:
            continue
        pool = candidates[size]
        picks = rng.choice(len(pool), size=need[size], replace=False)
        cases.extend(pool[i] for i in picks.tolist())
    return sorted(cases, key=lambda c: (bin(c).count("1"), c))


@pytest.mark.parametrize("seed", [0, 1, 2, 7, 12345])
def test_hand_example_draws(seed: int) -> None:
    cases = long_tail_cases(HAND_VISIBLE, np.random.default_rng(seed))
    expected = expected_draws(HAND_CANDIDATES, HAND_NEED, HAND_N, np.random.default_rng(seed))
    assert cases == expected
    # The forced part: 5 singletons and every size-2 candidate; then one of the two size-3 ones.
    assert cases[:9] == [1, 2, 4, 8, 16, 3, 6, 10, 20]
    assert len(cases) == 10 and cases[9] in (11, 28)


def test_hand_example_draws_from_the_case_stream() -> None:
    object_id = "0123456789abcdef" + "0" * 48
    for rotation in range(4):
        cases = long_tail_cases(HAND_VISIBLE, stream(3, object_id, rotation, Purpose.CASES))
        expected = expected_draws(HAND_CANDIDATES, HAND_NEED, HAND_N, stream(3, object_id, rotation, Purpose.CASES))
        assert cases == expected


def test_hand_example_seeds_differ_where_draws_are_free() -> None:
    outcomes = {tuple(long_tail_cases(HAND_VISIBLE, np.random.default_rng(seed))) for seed in range(32)}
    # Only the size-3 draw is free (1 of 2): both outcomes appear over 32 seeds.
    assert {o[-1] for o in outcomes} == {11, 28}
    assert len(outcomes) == 2


# A second hand example, with several free draws: a cycle of 10 keys, V_i = {2i, ..., 2i+4} mod 10.
#   V0 = {0,1,2,3,4}  V1 = {2,3,4,5,6}  V2 = {4,5,6,7,8}  V3 = {6,7,8,9,0}  V4 = {8,9,0,1,2}
# start 0: {0..4}; new V1 2, V2 4, V3 4, V4 2 -> V2; {0..8}; new V1 0, V3 1, V4 1 -> V3: full.
# start 1: {2..6}; new V0 2, V2 2, V3 4, V4 4 -> V3; missing {1}; new V0 1, V2 0, V4 1 -> V0: full.
# start 2: {4..8}; new V0 4, V1 2, V3 2, V4 4 -> V0; missing {9}; new V3 1, V4 1 -> V3: full.
# start 3: {6..9,0}; new V0 4, V1 4, V2 2, V4 2 -> V0; missing {5}; new V1 1, V2 1 -> V1: full.
# start 4: {8,9,0,1,2}; new V0 2, V1 4, V2 4, V3 2 -> V1; missing {7}; new V2 1, V3 1 -> V2: full.
# G = [25, 20, 5, 0, 0, 0]; size-2 candidates {0,2}=5 (twice), {1,3}=10, {0,3}=9, {1,4}=18
# -> [5, 9, 10, 18]; need(2) = ceil(5 * 5 / 20) = 2 of 4 (six possible pairs).
CYCLE_VISIBLE = [keys(*[(2 * i + k) % 10 for k in range(5)]) for i in range(5)]


def test_cycle_example() -> None:
    trajectories = greedy_trajectories(CYCLE_VISIBLE)
    assert trajectories.gains.tolist() == [25, 20, 5, 0, 0, 0]
    assert trajectories.candidates == {1: [1, 2, 4, 8, 16], 2: [5, 9, 10, 18]}
    assert [trajectories.need(m, 5) for m in range(1, 6)] == [5, 2, 0, 0, 0]
    outcomes = set()
    for seed in range(20):
        cases = long_tail_cases(CYCLE_VISIBLE, np.random.default_rng(seed))
        rng = np.random.default_rng(seed)
        picks = rng.choice(4, size=2, replace=False).tolist()
        assert cases == [1, 2, 4, 8, 16, *sorted([5, 9, 10, 18][i] for i in picks)]
        outcomes.add(tuple(cases))
    assert len(outcomes) >= 3


def test_every_view_sees_the_same_keys_gives_singletons_only() -> None:
    same = keys(3, 5, 8, 13)
    visible = [same.copy() for _ in range(6)]
    trajectories = greedy_trajectories(visible)
    assert trajectories.gains.tolist() == [24, 0, 0, 0, 0, 0, 0]
    assert trajectories.candidates == {}
    assert [trajectories.need(m, 6) for m in range(1, 7)] == [6, 0, 0, 0, 0, 0]
    assert long_tail_cases(visible, np.random.default_rng(0)) == [1 << v for v in range(6)]


def test_nested_views_g1_zero() -> None:
    # View 0 sees everything: trajectories from 0 end at once; the others take 0 next.
    visible = [keys(0, 1, 2, 3), keys(0, 1), keys(2), keys(1, 2, 3)]
    trajectories = greedy_trajectories(visible)
    # start 0: full at once. start 1: {0,1}; new V0 2, V2 1, V3 2 -> V0 (+2). start 2: {2};
    # new V0 3, V1 2, V3 2 -> V0 (+3). start 3: {1,2,3}; new V0 1, V1 1, V2 0 -> V0 (+1).
    assert trajectories.gains.tolist() == [4 + 2 + 1 + 3, 0 + 2 + 3 + 1, 0, 0, 0]
    assert trajectories.candidates == {1: [2, 4, 8]}
    assert [trajectories.need(m, 4) for m in range(1, 5)] == [4, 0, 0, 0]
    assert long_tail_cases(visible, np.random.default_rng(5)) == [1, 2, 4, 8]


def test_empty_views_and_no_keys() -> None:
    empty = [np.empty(0, dtype=np.int64) for _ in range(3)]
    assert greedy_trajectories(empty).gains.tolist() == [0, 0, 0, 0]
    assert long_tail_cases(empty, np.random.default_rng(0)) == [1, 2, 4]
    # A view that sees nothing still starts a trajectory (its first view gains 0).
    visible = [np.empty(0, dtype=np.int64), keys(1, 2), keys(2, 3)]
    trajectories = greedy_trajectories(visible)
    # start 0: {}; new V1 2, V2 2 -> V1; {1,2}; new V2 1 -> V2: full. start 1: {1,2} -> V2 (+1).
    # start 2: {2,3} -> V1 (+1).
    assert trajectories.gains.tolist() == [0 + 2 + 2, 2 + 1 + 1, 1, 0]
    assert trajectories.candidates == {1: [1, 2, 4], 2: [3]}
    assert trajectories.need(2, 3) == 1  # ceil(3 * 1 / 4) = 1
    assert long_tail_cases(visible, np.random.default_rng(0)) == [1, 2, 4, 3]


# ---------------------------------------------------------------------------------------------------------
# A plain reference implementation, written from docs/pipeline.md section 6
# ---------------------------------------------------------------------------------------------------------


def reference_trajectories(visible: list[np.ndarray]) -> tuple[list[int], dict[int, list[int]]]:
    sets = [set(v.tolist()) for v in visible]
    n = len(sets)
    full = set().union(*sets) if sets else set()
    gains = [0] * (n + 1)
    candidates: dict[int, set[int]] = {}
    for start in range(n):
        chosen, covered = [start], set(sets[start])
        gains[0] += len(covered)
        while len(covered) < len(full):
            candidates.setdefault(len(chosen), set()).add(mask(*chosen))
            best = max(range(n), key=lambda i: (len(sets[i] - covered), -i))
            gains[len(chosen)] += len(sets[best] - covered)
            covered |= sets[best]
            chosen.append(best)
    return gains, {size: sorted(c) for size, c in sorted(candidates.items())}


def reference_need(gains: list[int], candidates: dict[int, list[int]], size: int, n: int, capped: bool) -> int:
    if size == 1:
        return n
    if gains[1] == 0:
        return 0
    need = math.ceil(Fraction(n * gains[size], gains[1]))
    return min(need, len(candidates.get(size, []))) if capped else need


@st.composite
def visibility_sets(draw, max_views: int = 8, max_keys: int = 14) -> list[np.ndarray]:
    n = draw(st.integers(1, max_views))
    universe = draw(st.integers(1, max_keys))
    subsets = draw(st.lists(st.sets(st.integers(0, universe - 1)), min_size=n, max_size=n))
    # Spread keys apart and offset them, as packed keys are (order is all that matters).
    return [np.array(sorted(1000 + 37 * k for k in s), dtype=np.int64) for s in subsets]


@settings(max_examples=300, deadline=None)
@given(visibility_sets())
def test_greedy_matches_reference(visible: list[np.ndarray]) -> None:
    trajectories = greedy_trajectories(visible)
    gains, candidates = reference_trajectories(visible)
    assert trajectories.gains.tolist() == gains
    assert trajectories.candidates == candidates
    n = len(visible)
    union = len(set().union(*[set(v.tolist()) for v in visible]))
    assert int(trajectories.gains.sum()) == n * union  # each trajectory's gains sum to |union|
    for size in range(1, n + 1):
        for capped in (True, False):
            assert trajectories.need(size, n, capped) == reference_need(gains, candidates, size, n, capped)


@settings(max_examples=300, deadline=None)
@given(visibility_sets(max_views=10, max_keys=20))
def test_uncapped_need_never_increases(visible: list[np.ndarray]) -> None:
    n = len(visible)
    trajectories = greedy_trajectories(visible)
    needs = [trajectories.need(m, n, capped=False) for m in range(1, n + 1)]
    assert needs[0] == n
    assert all(later <= earlier for earlier, later in pairwise(needs)), needs
    # Behind it: for m >= 1 the total gains never increase (greedy gains are non-increasing).
    g = trajectories.gains.tolist()
    assert all(later <= earlier for earlier, later in pairwise(g[1:])), g


@settings(max_examples=200, deadline=None)
@given(visibility_sets(), st.integers(0, 2**32 - 1))
def test_long_tail_case_invariants(visible: list[np.ndarray], seed: int) -> None:
    n = len(visible)
    trajectories = greedy_trajectories(visible)
    cases = long_tail_cases(visible, np.random.default_rng(seed))
    assert len(set(cases)) == len(cases)
    sizes = [c.bit_count() for c in cases]
    assert sorted(c for c in cases if c.bit_count() == 1) == [1 << v for v in range(n)]
    assert cases == sorted(cases, key=lambda c: (c.bit_count(), c))
    for case in cases:
        assert case.bit_count() == 1 or case in trajectories.candidates[case.bit_count()]
    for size in range(1, n + 1):
        assert sizes.count(size) == trajectories.need(size, n)
    assert case_sizes(cases).tolist() == sizes
    assert long_tail_cases(visible, np.random.default_rng(seed)) == cases
    expected = expected_draws(
        trajectories.candidates,
        {m: trajectories.need(m, n) for m in range(1, n + 1)},
        n,
        np.random.default_rng(seed),
    )
    assert cases == expected


def test_sixty_four_views() -> None:
    # V_i = {i, 100}: every trajectory adds the lowest unchosen views one key at a time until all
    # 64 are chosen. G[0] = 64 * 2, G[m] = 64 for m = 1..63. Size-m candidates: {0..m-1} (from
    # starts 0..m-1) and {0..m-2} + {s} for s = m..63: 65 - m distinct; need(m) = 64, capped.
    n = 64
    visible = [keys(i, 100) for i in range(n)]
    trajectories = greedy_trajectories(visible)
    assert trajectories.gains.tolist() == [128] + [64] * 63 + [0]
    for size in range(2, n):
        assert len(trajectories.candidates[size]) == 65 - size
        assert trajectories.need(size, n) == 65 - size
    cases = long_tail_cases(visible, np.random.default_rng(0))
    assert len(cases) == 64 + sum(65 - m for m in range(2, 64))
    assert cases[63] == 1 << 63
    assert cases[-2:] == [mask(*range(63)), mask(*range(62), 63)]  # both size-63 candidates, by mask
    assert trajectories.candidates == reference_trajectories(visible)[1]


def test_trajectories_need_edge_cases() -> None:
    t = Trajectories(gains=np.array([3, 0, 0, 0], dtype=np.int64), candidates={})
    assert [t.need(m, 3) for m in (1, 2, 3)] == [3, 0, 0]
    t = Trajectories(gains=np.array([9, 4, 1, 0], dtype=np.int64), candidates={2: [3, 5, 6]})
    assert t.need(2, 3, capped=False) == 1  # ceil(3 / 4)
    assert t.need(2, 3) == 1
    assert t.need(3, 3) == 0  # no candidate and G[3] = 0
