"""Key-set helpers against numpy's own set routines (the independent truth)."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.pipeline.keys import pack_keys, sorted_unique, union_keys


@pytest.mark.parametrize("dtype", [np.int64, np.uint64, np.int32])
def test_sorted_unique_equals_numpy_unique(dtype: type) -> None:
    rng = np.random.default_rng(3)
    for size in (0, 1, 2, 17, 5000):
        values = rng.integers(0, 50 if size > 2 else 3, size=size).astype(dtype)
        got = sorted_unique(values)
        want = np.unique(values)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)


def test_sorted_unique_of_negative_packed_keys_and_a_2d_array() -> None:
    rng = np.random.default_rng(4)
    keys = pack_keys(rng.integers(-300, 300, size=(4000, 3)))
    np.testing.assert_array_equal(sorted_unique(keys), np.unique(keys))
    grid = rng.integers(-5, 5, size=(30, 7))
    np.testing.assert_array_equal(sorted_unique(grid), np.unique(grid))


def test_union_keys_is_union1d_of_every_set() -> None:
    rng = np.random.default_rng(5)
    sets = [np.unique(pack_keys(rng.integers(-40, 40, size=(n, 3)))) for n in (0, 10, 900, 2500)]
    want = sets[0]
    for keys in sets[1:]:
        want = np.union1d(want, keys)
    np.testing.assert_array_equal(union_keys(*sets), want)
    assert union_keys().dtype == np.int64 and union_keys().size == 0
