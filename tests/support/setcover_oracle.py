"""An independent brute-force oracle for labels (docs/pipeline.md section 7). It never imports
``datagen.pipeline.setcover``.

The label of a universe (rows = bit masks of the views covering each element) is the
lexicographically smallest sorted tuple among the minimum-cardinality covers. The oracle finds it
the obvious way: for k = 0, 1, 2, ... it enumerates every sorted k-tuple of views in lexicographic
order (``itertools.combinations`` of sorted views yields exactly that order) and returns the first
tuple that covers every row. Coverage is tested with bitsets: each view's column is the set of rows
it covers, packed into bytes, and a tuple covers everything when the OR of its columns is all ones.
Tuples are tested in vectorised chunks; chunks are consumed in order, so the first hit of the
first chunk with a hit is the lexicographically first cover.

The only shortcuts, each trivially sound:
- identical rows are one row (a set covers a row iff it covers its copy);
- views that cover no row are never enumerated (a minimum cover never contains one: dropping it
  would leave a smaller cover).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

CHUNK = 8192
"""Tuples tested per vectorised step."""


@dataclass(frozen=True)
class OracleCover:
    label: int
    """Bit mask of the lexicographically smallest minimum cover."""
    size: int
    """The minimum cardinality."""
    ties: int
    """How many covers have the minimum cardinality (1 = no tie to break); only counted when
    asked for, else -1."""
    every: tuple[int, ...] = ()
    """Every minimum cover (masks, in lexicographic order of their view tuples) when counted."""

    @property
    def views(self) -> tuple[int, ...]:
        return tuple(v for v in range(self.label.bit_length()) if self.label >> v & 1)


class NoCover(Exception):
    """Some row is covered by no allowed view."""


def oracle_cover(rows: Iterable[int], allowed: int | None = None, count_ties: bool = False) -> OracleCover:
    """The lexicographically smallest minimum-cardinality cover of ``rows`` (Python ints) using
    only views in the mask ``allowed`` (default: every view)."""
    distinct = sorted({int(r) for r in rows})
    if not distinct:
        return OracleCover(0, 0, 1, (0,)) if count_ties else OracleCover(0, 0, -1)
    if allowed is not None:
        distinct = sorted({r & allowed for r in distinct})
    if distinct[0] == 0:
        raise NoCover("a row is covered by no allowed view")
    union = 0
    for r in distinct:
        union |= r
    views = [v for v in range(union.bit_length()) if union >> v & 1]
    # columns[j]: which rows view views[j] covers, packed into bytes.
    incidence = np.array([[r >> v & 1 for r in distinct] for v in views], dtype=bool)
    columns = np.packbits(incidence, axis=1)
    full = np.packbits(np.ones(len(distinct), dtype=bool))
    for k in range(1, len(views) + 1):
        found: tuple[int, ...] | None = None
        ties = 0
        every: list[int] = []
        tuples = itertools.combinations(range(len(views)), k)
        while True:
            chunk = np.fromiter(itertools.chain.from_iterable(itertools.islice(tuples, CHUNK)), dtype=np.int64)
            if chunk.size == 0:
                break
            chunk = chunk.reshape(-1, k)
            covered = columns[chunk[:, 0]].copy()
            for j in range(1, k):
                covered |= columns[chunk[:, j]]
            hits = np.flatnonzero((covered == full[None, :]).all(axis=1))
            if hits.size:
                if found is None:
                    found = tuple(int(i) for i in chunk[hits[0]])
                ties += int(hits.size)
                every += [sum(1 << views[int(i)] for i in chunk[hit]) for hit in hits]
                if not count_ties:
                    break
        if found is not None:
            label = 0
            for index in found:
                label |= 1 << views[index]
            return OracleCover(label, k, ties, tuple(every)) if count_ties else OracleCover(label, k, -1)
    raise AssertionError("unreachable: all views together cover every row")


def oracle_minimum_covers(rows: Iterable[int]) -> list[int]:
    """Every minimum-cardinality cover of ``rows`` (masks, in lexicographic order of view tuples)."""
    return list(oracle_cover(rows, count_ties=True).every)


def oracle_minimal(rows: Iterable[int]) -> list[int]:
    """The distinct rows that contain no other distinct row, sorted (quadratic, obvious)."""
    distinct = sorted({int(r) for r in rows})
    return [r for r in distinct if not any(o != r and o & r == o for o in distinct)]


def covers(label: int, rows: Iterable[int]) -> bool:
    return all(int(r) & label for r in rows)
