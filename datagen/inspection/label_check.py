"""Check stored labels against a solve of our own (docs/pipeline.md sections 5 and 7).

`storage.validate` only asks whether a label covers its U. Here every checked label must also be a
minimum cover and, among the minimum covers, the lexicographically smallest tuple of views in the
dataset's tie-break order (by index, or by coverage of U: `setcover.view_order`, whose ranking is
recounted here from the stored sets);
the index must hold the same label as the shard. The coverage is rebuilt from the shard's stored P_i
at the dataset's alpha, and the expected label is found by other means than `datagen.pipeline.setcover`
(greedy and LP bounds, a MIP, a pruned depth-first search), so a bug there cannot hide here:

- views forced by single-view rows are in every cover and are taken first;
- smaller sizes than the label's are ruled out by trying every combination of the remaining views
  (bitsets, vectorised), or by one HiGHS MIP when there are more than `SEARCH_LIMIT`;
- at the minimum size, combinations are tried in lexicographic order (`itertools.combinations`
  order) up to the label's own position: the first cover is the answer, by definition. When that
  position is too far, views are fixed in ascending order instead, each kept while a cover of the
  minimum size still exists with it (one HiGHS feasibility model per view).
"""

from __future__ import annotations

import itertools
import math
import threading
import zlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Protocol

import highspy
import numpy as np
import numpy.typing as npt

from datagen.pipeline import setcover
from schemas.config import MAX_VIEWS, GenerationConfig
from schemas.index import CommitRecord
from schemas.objectives import objective_named
from schemas.shard import COVERS, LABEL_COLUMN, MASK_DTYPE, MASKS, VIEW_STATE_COLUMN, keys_array, offsets_array
from storage import (
    SAMPLED_ROWS_PER_SHARD,
    DamagedFile,
    Location,
    ShardReader,
    open_location,
    read_info,
    undominated,
)
from storage.index import index_rows_of
from storage.manifest import task_records

MaskArray = npt.NDArray[np.uint64]

SEARCH_LIMIT = 2_000_000
"""Most view combinations tried by enumeration for one label; beyond it HiGHS decides."""
DENSE_CELLS = 1 << 24
"""Largest key bounding box (cells) `full_masks` covers with a dense grid (128 MiB of uint64)."""
READ_THREADS = 2
TASK_CHUNK = 512
"""Tasks whose index rows the checks hold at once."""
"""Shards checked at once (their reads overlap; results keep the task order)."""
CHUNK = 4096
"""Combinations tested per vectorised step."""
TIME_LIMIT = 30.0
"""Seconds per HiGHS model; a model not solved in time is reported, never guessed."""

HIGHS_LOCK = threading.Lock()
"""Held around every HiGHS run of the checks (shards are checked on a few threads)."""

UNREADABLE = "unreadable"
UNCOVERED = "uncovered"
NOT_MINIMUM = "not-minimum"
NOT_LEXICOGRAPHIC = "not-lexicographic"
INDEX_MISMATCH = "index-mismatch"
UNSOLVED = "unsolved"
COVERS_WRONG = "covers"
"""A version-2 sample's minimum covers, their count or support differ from an enumeration of our own."""

AMBIGUITY_COLUMNS = ("label_support", "min_covers", "min_covers_exact")
NEXT_VIEW_COLUMNS = ("visible_size", "best_view", "best_view_ties", "best_gain")

Progress = Callable[[int, int], None]
"""Called with (shards done, shards in all) after each shard."""


@dataclass(frozen=True)
class LabelProblem:
    """One line of the report, with where it is, so callers can merge it with storage's lines."""

    shard: str
    row: int | None
    """Row in the shard; None for a problem with the whole shard."""
    kind: str
    line: str


@dataclass
class LabelReport:
    problems: list[LabelProblem] = field(default_factory=list)
    checked: int = 0
    """Labels checked with the solver."""
    shards: int = 0


@dataclass(frozen=True)
class Ambiguity:
    """A sample's stored minimum covers with the index's support and count."""

    listed: tuple[int, ...]
    support: int
    count: int
    exact: bool


@dataclass(frozen=True)
class Expected:
    """The label the rules call for: the lexicographically smallest minimum cover of U."""

    size: int
    label: int


def views_text(mask: int) -> str:
    """A mask as the set of its views, e.g. ``{3, 17}``."""
    return "{" + ", ".join(str(v) for v in range(mask.bit_length()) if mask >> v & 1) + "}"


# ---------------------------------------------------------------------------------------------------------
# the dataset
# ---------------------------------------------------------------------------------------------------------


def check_labels(
    url: str,
    full: bool = False,
    seed: int = 0,
    storage_options: dict[str, Any] | None = None,
    progress: Progress | None = None,
    search_limit: int = SEARCH_LIMIT,
) -> LabelReport:
    """Check every label (``full``) or a seeded sample of `SAMPLED_ROWS_PER_SHARD` per shard.

    Raises `StorageError` when ``dataset.json`` cannot be read; a shard that cannot be read is one
    problem line and the others are still checked. (`datagen shards validate` runs the same checks
    as `storage.validate`'s per-shard hook instead, reading each shard once.)
    """
    location = open_location(url, storage_options)
    tasks = task_records(location)
    report = LabelReport(shards=len(tasks.records))
    done = 0
    for start in range(0, len(tasks.records), TASK_CHUNK):  # the index rows of a chunk at a time
        chunk = tasks.records[start : start + TASK_CHUNK]
        checker = ShardLabelCheck(location, full, seed, search_limit, records=chunk)

        def check(record: CommitRecord, checker: ShardLabelCheck = checker) -> list[LabelProblem]:
            try:
                shard = ShardReader(location, record.shard, span=tasks.spans.get(record.shard))
            except Exception as exc:  # storage.validate names the damage; here it only stops the label checks
                line = f"{record.shard}: cannot check labels ({_why(exc)})"
                return [LabelProblem(record.shard, None, UNREADABLE, line)]
            checker(record, shard)
            return []

        # Reading a shard mostly waits on storage (zarr's event loop, decompression): overlap a few.
        with ThreadPoolExecutor(max_workers=READ_THREADS) as pool:
            for unreadable in pool.map(check, chunk):
                checker.report.problems.extend(unreadable)
                done += 1
                if progress:
                    progress(done, len(tasks.records))
        report.problems.extend(checker.report.problems)
        report.checked += checker.report.checked
    return finish_report(report)


def finish_report(report: LabelReport) -> LabelReport:
    """The report with its problems sorted by shard, row, kind and line."""
    report.problems.sort(key=lambda p: (p.shard, -1 if p.row is None else p.row, p.kind, p.line))
    return report


class ShardLabelCheck:
    """The label checks of some tasks as a `storage.validate` shard hook: each shard is read once, for
    both. ``records``: the tasks it is handed (their index rows are read for them alone).

    Findings go to ``report`` (sorted by shard and row once `finish` is called); the rows checked in
    a shard are drawn as `check_labels` draws them, so both paths judge the same labels.
    """

    def __init__(
        self,
        location: Location,
        full: bool,
        seed: int = 0,
        search_limit: int = SEARCH_LIMIT,
        records: Sequence[CommitRecord] = (),
    ) -> None:
        info = read_info(location)
        self.location = location
        self.config = info.config
        self.alpha, self.num_views = info.config.alpha, info.num_views
        self.tie_break = info.config.label_tie_break
        self.full, self.seed, self.search_limit = full, seed, search_limit
        self.index_rows = IndexRows(location, records)
        self.positions = np.asarray(info.view_positions, dtype=np.float64)
        self.report = LabelReport(shards=len(records))
        self._lock = threading.Lock()

    def __call__(self, record: CommitRecord, shard: ShardReader) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, zlib.crc32(record.task_id.encode())]))
        problems, checked = _check_reader(
            shard,
            record,
            self.alpha,
            self.num_views,
            self.full,
            rng,
            self.index_rows,
            self.search_limit,
            self.tie_break,
            self.config,
        )
        if self.full and shard.attributes.schema_version >= 3:
            problems += self._next_view(record, shard)
        with self._lock:
            self.report.problems.extend(problems)
            self.report.checked += checked

    def _next_view(self, record: CommitRecord, shard: ShardReader) -> list[LabelProblem]:
        """The grid walked again and the index's best views (version 3, ``--all`` only)."""
        from datagen.inspection.next_view_check import next_view_problems

        count = shard.attributes.num_samples
        indexed = [getattr(self.index_rows.get((record.shard, row)), "next_view", None) for row in range(count)]
        try:
            found = next_view_problems(shard, self.config, self.positions, indexed)
        except Exception as exc:  # storage.validate names the damage; here it only stops these checks
            return [
                LabelProblem(record.shard, None, UNREADABLE, f"{record.shard}: cannot check the grid ({_why(exc)})")
            ]
        return [
            LabelProblem(record.shard, row, kind, f"{record.shard}{'' if row is None else f' row {row}'}: {text}")
            for row, kind, text in found
        ]

    def finish(self) -> LabelReport:
        return finish_report(self.report)


@dataclass(frozen=True)
class IndexRow:
    """What the index says of one sample."""

    sample_id: str
    label: int
    ambiguity: tuple[int, int, bool] | None
    """(support, count of minimum covers, whether the count is exact) in a version-2 index."""
    next_view: tuple[int, int, int, int] | None = None
    """(visible size, best view, views sharing its gain, that gain) in a version-3 index."""


class IndexRows:
    """(shard, row) -> what the index holds (`IndexRow`) for some tasks' samples, read for them alone
    (`storage.index.index_rows_of`: the manifest's row groups that hold them): the whole index as Python
    objects would take gigabytes at millions of samples. Empty when the index cannot be read
    (`storage.validate` says why)."""

    def __init__(self, location: Location, records: Sequence[CommitRecord]) -> None:
        self._rows: dict[tuple[str, int], IndexRow] = {}
        if not records:
            return
        try:
            columns = index_columns(location)
            table = index_rows_of(location, records, ["shard", "row", "sample_id", "label", *columns])
        except Exception:
            return
        values = {name: table.column(name).to_pylist() for name in table.column_names}
        ambiguity = (
            zip(*(values[c] for c in AMBIGUITY_COLUMNS), strict=True) if AMBIGUITY_COLUMNS[0] in values else None
        )
        views = zip(*(values[c] for c in NEXT_VIEW_COLUMNS), strict=True) if NEXT_VIEW_COLUMNS[0] in values else None
        for shard, row, name, label in zip(
            values["shard"], values["row"], values["sample_id"], values["label"], strict=True
        ):
            a = next(ambiguity) if ambiguity is not None else None
            v = next(views) if views is not None else None
            self._rows[(shard, int(row))] = IndexRow(
                name,
                int(label),
                (int(a[0]), int(a[1]), bool(a[2])) if a is not None else None,
                (int(v[0]), int(v[1]), int(v[2]), int(v[3])) if v is not None else None,
            )

    def get(self, key: tuple[str, int]) -> IndexRow | None:
        return self._rows.get(key)


def index_columns(location: Location) -> list[str]:
    """The optional columns the label checks compare (ambiguity, next view) that the dataset's index has."""
    from schemas.index import INDEX_SCHEMAS

    names = INDEX_SCHEMAS[read_info(location).schema_version].names
    return [name for name in (*AMBIGUITY_COLUMNS, *NEXT_VIEW_COLUMNS) if name in names]


def _why(error: Exception) -> str:
    """What is wrong with a shard, without the reader's advice to run the validation running now."""
    if isinstance(error, DamagedFile):
        return f"{error.relative}: {error.problem}"
    return f"{type(error).__name__}: {error}"


def _sample_id(task_id: str, case: int) -> str:
    """The id of a sample the index does not name (imported late: `datagen.pipeline.task` loads the pipeline)."""
    from datagen.pipeline.task import sample_id

    return sample_id(task_id, case)


def _check_reader(
    shard: ShardReader,
    record: CommitRecord,
    alpha: int,
    num_views: int,
    full: bool,
    rng: np.random.Generator,
    index_rows: IndexRows,
    search_limit: int,
    tie_break: setcover.TieBreak = "index",
    config: GenerationConfig | None = None,
) -> tuple[list[LabelProblem], int]:
    """The label problems of an open shard and how many labels were checked (``config``: the dataset's,
    for its label objective; None reads as the paper's cover objective)."""
    where = record.shard
    objective = config.objective if config is not None else objective_named("cover")
    try:
        masks = shard.array(MASKS)
        keys, offsets = _task_sets(shard, objective.judged_on, num_views)
    except Exception as exc:  # storage.validate names the damage; here it only stops the label checks
        line = f"{where}: cannot check labels ({_why(exc)})"
        return [LabelProblem(where, None, UNREADABLE, line)], 0
    if masks.dtype != MASK_DTYPE or masks.ndim != 2 or masks.shape[1] != 2:
        return [LabelProblem(where, None, UNREADABLE, f"{where}: cannot check labels (masks {masks.shape})")], 0
    stored = StoredSets(keys, offsets, alpha, num_views, search_limit, tie_break, config)
    cover: LabelChecker = objective.load_checker()(stored)
    listed = _listed_covers(shard, masks.shape[0])
    count = masks.shape[0]
    rows = np.arange(count) if full else np.sort(rng.permutation(count)[:SAMPLED_ROWS_PER_SHARD])
    problems: list[LabelProblem] = []
    for row in rows.tolist():
        case, label = int(masks[row, VIEW_STATE_COLUMN]), int(masks[row, LABEL_COLUMN])
        indexed = index_rows.get((where, row))
        name = indexed.sample_id if indexed else _sample_id(shard.attributes.task_id, case)
        judged = list(cover.judge(case, label))
        problems.extend(LabelProblem(where, row, kind, f"{name}: {text}") for kind, text in judged)
        if indexed is not None and indexed.label != label:
            text = f"the index says label {views_text(indexed.label)}, the shard holds {views_text(label)}"
            problems.append(LabelProblem(where, row, INDEX_MISMATCH, f"{name}: {text}"))
        if listed is not None and not judged and indexed is not None and indexed.ambiguity is not None:
            ambiguity = Ambiguity(listed[row], *indexed.ambiguity)
            problems.extend(
                LabelProblem(where, row, kind, f"{name}: {text}")
                for kind, text in cover.judge_covers(case, label, ambiguity)
            )
    return problems, int(rows.size)


def _listed_covers(shard: ShardReader, count: int) -> list[tuple[int, ...]] | None:
    """Each sample's stored minimum covers (version 2), None for a version-1 shard."""
    if shard.attributes.schema_version < 2:
        return None
    covers, offsets = shard.array(COVERS), shard.array(offsets_array(COVERS))
    if offsets.shape != (count + 1,):
        raise ValueError(f"covers offsets {offsets.shape} do not match {count} samples")
    return [tuple(int(c) for c in covers[offsets[i] : offsets[i + 1]]) for i in range(count)]


def _task_sets(shard: ShardReader, name: str, num_views: int) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.int64]]:
    """The stored P_i (``refined``) or V_i (``visible``), keys and offsets, refusing offsets that do not
    describe the key array."""
    keys, offsets = shard.array(keys_array(name)), shard.array(offsets_array(name))
    if offsets.shape != (num_views + 1,) or offsets[0] != 0 or offsets[-1] != keys.shape[0]:
        raise ValueError(f"{name} offsets {offsets.shape} do not match {keys.shape[0]} keys and {num_views} views")
    if (np.diff(offsets) < 0).any():
        raise ValueError(f"{name} offsets are not monotone")
    if keys.ndim != 2 or keys.shape[1] != 3:
        raise ValueError(f"{name} keys have shape {keys.shape}")
    return keys, offsets


def full_masks(keys: npt.NDArray[np.integer], offsets: npt.NDArray[np.int64], alpha: int) -> MaskArray:
    """For each key of P_full (in at least ``alpha`` of the P_i), the mask of the views holding it.

    Each view ORs its bit into its keys' cells of a dense grid over the keys' bounding box (no sort;
    a few milliseconds a task); a box too large for memory falls back to sorting the cell numbers.
    """
    if keys.shape[0] == 0:
        return np.empty(0, dtype=np.uint64)
    k = keys.astype(np.int64)
    low = k.min(axis=0)
    extent = k.max(axis=0) - low + 1
    cells = ((k[:, 0] - low[0]) * extent[1] + (k[:, 1] - low[1])) * extent[2] + (k[:, 2] - low[2])
    volume = int(np.prod(extent))
    if volume <= DENSE_CELLS:
        grid = np.zeros(volume, dtype=np.uint64)
        for view in range(offsets.size - 1):
            grid[cells[offsets[view] : offsets[view + 1]]] |= np.uint64(1) << np.uint64(view)
        masks = grid[grid != 0]
    else:
        views = np.repeat(np.arange(offsets.size - 1, dtype=np.uint64), np.diff(offsets))
        distinct, inverse = np.unique(cells, return_inverse=True)
        masks = np.zeros(distinct.size, dtype=np.uint64)
        np.bitwise_or.at(masks, inverse, np.uint64(1) << views)
    return masks[np.bitwise_count(masks) >= alpha]


# ---------------------------------------------------------------------------------------------------------
# one task's rows and one label
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StoredSets:
    """One shard's stored per-view key sets of the kind its objective is judged on (P_i or V_i), and
    what a checker of its labels needs besides."""

    keys: npt.NDArray[np.int16]
    offsets: npt.NDArray[np.int64]
    alpha: int
    num_views: int
    search_limit: int
    tie_break: setcover.TieBreak
    config: GenerationConfig | None


class LabelChecker(Protocol):
    """An objective's independent check of stored labels (`schemas.objectives.Objective.checker`)."""

    def judge(self, case: int, label: int) -> Iterator[tuple[str, str]]:
        """(kind, text) for each rule the label breaks."""
        ...

    def judge_covers(self, case: int, label: int, stored: Ambiguity) -> Iterator[tuple[str, str]]:
        """(kind, text) where the stored ties, their count or support are not what exists."""
        ...


def cover_checker(stored: StoredSets) -> TaskRows:
    """The ``cover`` objective's checker: P_full's rows, every minimum cover enumerated."""
    masks = full_masks(stored.keys, stored.offsets, stored.alpha)
    return TaskRows.from_masks(masks, stored.search_limit, stored.tie_break, stored.num_views)


class TaskRows:
    """The P_full masks of one task: distinct masks with their key counts, and the undominated ones.

    For a case S, U's keys are those whose mask misses S; U's undominated masks are exactly the
    task's undominated masks that miss S (a subset of a mask missing S misses S too), so the
    reduction is done once per task.
    """

    def __init__(
        self,
        distinct: MaskArray,
        counts: npt.NDArray[np.int64],
        search_limit: int = SEARCH_LIMIT,
        tie_break: setcover.TieBreak = "index",
        num_views: int = MAX_VIEWS,
    ) -> None:
        self.distinct = distinct
        self.counts = counts
        self.undominated = undominated(distinct)
        self.search_limit = search_limit
        self.tie_break = tie_break
        self.num_views = num_views

    @classmethod
    def from_masks(
        cls,
        masks: npt.ArrayLike,
        search_limit: int = SEARCH_LIMIT,
        tie_break: setcover.TieBreak = "index",
        num_views: int = MAX_VIEWS,
    ) -> TaskRows:
        distinct, counts = np.unique(np.asarray(masks, dtype=np.uint64), return_counts=True)
        return cls(distinct, counts.astype(np.int64), search_limit, tie_break, num_views)

    def view_order(self, case: int) -> list[int] | None:
        """The tie-break's view order for case S (None: by index), from U's keys with their counts."""
        if self.tie_break == "index":
            return None
        in_universe = (self.distinct & np.uint64(case)) == 0
        counts = setcover.coverage_counts(self.distinct[in_universe], self.counts[in_universe], self.num_views)
        return setcover.view_order(counts)

    def judge(self, case: int, label: int) -> Iterator[tuple[str, str]]:
        """(kind, text) for each rule the label breaks; nothing when it is the expected label."""
        in_universe = (self.distinct & np.uint64(case)) == 0
        missed = in_universe & ((self.distinct & np.uint64(label)) == 0)
        if missed.any():
            uncovered, total = int(self.counts[missed].sum()), int(self.counts[in_universe].sum())
            yield UNCOVERED, f"label {views_text(label)} does not cover U ({uncovered} of {total} keys uncovered)"
            return
        rows = self.undominated[(self.undominated & np.uint64(case)) == 0]
        try:
            expected = expected_label(rows, label, self.search_limit, self.view_order(case))
        except SolverFailure as exc:
            yield UNSOLVED, f"label {views_text(label)} could not be checked ({exc})"
            return
        size = label.bit_count()
        if size > expected.size:
            yield NOT_MINIMUM, f"label {views_text(label)} covers U but is not minimum (k={size} > k*={expected.size})"
        elif size < expected.size:
            yield UNSOLVED, f"label {views_text(label)} covers U with k={size} < k*={expected.size}: the check is wrong"
        elif label != expected.label:
            choice = "lexicographic" if self.tie_break == "index" else f"{self.tie_break} tie-break's"
            text = f"label {views_text(label)} is minimum but not the {choice} choice {views_text(expected.label)}"
            yield NOT_LEXICOGRAPHIC, text

    def judge_covers(self, case: int, label: int, stored: Ambiguity) -> Iterator[tuple[str, str]]:
        """(kind, text) where the stored minimum covers, their count or support differ from an
        enumeration of every view set of the label's size (the label already judged minimum)."""
        rows = self.undominated[(self.undominated & np.uint64(case)) == 0]
        try:
            expected = every_minimum_cover(rows, label.bit_count(), self.search_limit)
        except SolverFailure as exc:
            yield UNSOLVED, f"minimum covers of label {views_text(label)} could not be checked ({exc})"
            return
        support = 0
        for found in expected.covers:
            support |= found
        if expected.complete:
            count, listed = len(expected.covers), set(expected.covers)
            if stored.exact and stored.count != count:
                yield COVERS_WRONG, f"the index counts {stored.count} minimum covers, there are {count}"
            elif not stored.exact and stored.count > count:
                yield COVERS_WRONG, f"the index says at least {stored.count} minimum covers, there are {count}"
            if stored.exact and set(stored.listed) != listed:
                yield COVERS_WRONG, f"the {len(stored.listed)} listed minimum covers are not the {count} that exist"
            elif not set(stored.listed) <= listed:
                yield COVERS_WRONG, "a listed cover is not a minimum cover"
        else:
            support = _support_by_highs(rows, label.bit_count())
        if stored.support != support:
            yield COVERS_WRONG, f"support {views_text(stored.support)}, the minimum covers use {views_text(support)}"


@dataclass(frozen=True)
class AllCovers:
    covers: list[int]
    """Every minimum cover found; all of them when ``complete``."""
    complete: bool


def every_minimum_cover(rows: MaskArray, size: int, search_limit: int = SEARCH_LIMIT) -> AllCovers:
    """Every cover of ``rows`` by ``size`` views (the minimum size), by trying each combination of the
    views left after the forced ones (single-view rows); incomplete past ``search_limit`` combinations."""
    if rows.size == 0:
        return AllCovers([0], True)
    singles = rows[np.bitwise_count(rows) == 1]
    forced = int(np.bitwise_or.reduce(singles)) if singles.size else 0
    rest = rows[(rows & np.uint64(forced)) == 0]
    if rest.size == 0:
        return AllCovers([forced], True)
    union = int(np.bitwise_or.reduce(rest))
    candidates = [v for v in range(union.bit_length()) if union >> v & 1]
    free = size - forced.bit_count()
    if math.comb(len(candidates), free) > search_limit:
        return AllCovers([], False)
    return AllCovers([forced | c for c in _Bitsets(rest, candidates).every(free)], True)


def _support_by_highs(rows: MaskArray, size: int) -> int:
    """Views in some cover of ``size`` views, asked of HiGHS one view at a time."""
    union = int(np.bitwise_or.reduce(rows))
    candidates = [v for v in range(union.bit_length()) if union >> v & 1]
    support = 0
    for view in candidates:
        if _min_cover_size(rows, candidates, {view: 1}, exactly=size) == size:
            support |= 1 << view
    return support


class SolverFailure(Exception):
    """HiGHS did not prove its answer (time limit or error): the label is neither passed nor failed."""


def expected_label(
    rows: MaskArray, label: int, search_limit: int = SEARCH_LIMIT, order: Sequence[int] | None = None
) -> Expected:
    """The lexicographically smallest minimum cover of ``rows`` (views compared in ``order``, by
    index when None), given ``label``, a cover, as a bound.

    Sizes below |label| are ruled out by trying every combination (or by HiGHS when there are too
    many); at the minimum size, combinations are tried in lexicographic order up to the label's own
    position (or views are fixed one at a time with HiGHS when that position is too far).
    """
    if rows.size == 0:
        return Expected(0, 0)
    if (rows == 0).any():
        raise SolverFailure("a key of U is seen by no view")
    if not bool(((rows & np.uint64(label)) != 0).all()):
        raise SolverFailure("the label does not cover U")
    singles = rows[np.bitwise_count(rows) == 1]
    forced = int(np.bitwise_or.reduce(singles)) if singles.size else 0
    rest = rows[(rows & np.uint64(forced)) == 0]
    if rest.size == 0:
        return Expected(forced.bit_count(), forced)
    union = int(np.bitwise_or.reduce(rest))
    ranking = range(union.bit_length()) if order is None else order
    candidates = [v for v in ranking if union >> v & 1]
    free = label & union  # the label's views that cover something forced views leave open
    cover = _Bitsets(rest, candidates)
    size, m = free.bit_count(), len(candidates)
    if sum(math.comb(m, j) for j in range(1, size)) <= search_limit:
        for smaller in range(1, size):
            found = cover.first(smaller, math.comb(m, smaller))
            if found is not None:
                return Expected(forced.bit_count() + smaller, forced | found)
    else:
        minimum = _min_cover_size(rest, candidates, {})
        if minimum is None:
            raise SolverFailure("HiGHS finds no cover")
        size = min(size, minimum)
    if size == free.bit_count():
        positions = [candidates.index(v) for v in candidates if free >> v & 1]
        tries = lexicographic_rank(positions, m) + 1
    else:
        tries = math.comb(m, size)
    found = cover.first(size, tries) if tries <= search_limit else None
    if found is None:
        found = _highs_lexicographic(rest, candidates, size)
    return Expected(forced.bit_count() + size, forced | found)


def lexicographic_rank(positions: Sequence[int], m: int) -> int:
    """Rank of a sorted k-combination of range(m) in lexicographic order (0 for (0, 1, .., k-1))."""
    k, rank, previous = len(positions), 0, -1
    for i, p in enumerate(positions):
        rank += sum(math.comb(m - 1 - q, k - 1 - i) for q in range(previous + 1, p))
        previous = p
    return rank


class _Bitsets:
    """For each candidate view, the rows it covers as a bitset (uint64 words): a combination covers
    every row when the OR of its views' bitsets is all ones."""

    def __init__(self, rows: MaskArray, candidates: list[int]) -> None:
        self.candidates = candidates
        incidence = ((rows[None, :] >> np.array(candidates, dtype=np.uint64)[:, None]) & np.uint64(1)).astype(bool)
        self.columns = self._pack(incidence)
        self.full = self._pack(np.ones((1, rows.size), dtype=bool))[0]

    @staticmethod
    def _pack(bits: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint64]:
        packed = np.packbits(bits, axis=1, bitorder="little")
        padded = np.zeros((packed.shape[0], -(-packed.shape[1] // 8) * 8), dtype=np.uint8)
        padded[:, : packed.shape[1]] = packed
        return padded.view(np.uint64)

    def every(self, size: int) -> list[int]:
        """Masks of every ``size``-combination that covers all rows."""
        found: list[int] = []
        for combinations in _combination_chunks(len(self.candidates), size):
            covered = np.bitwise_or.reduce(self.columns[combinations], axis=1)
            for hit in np.flatnonzero((covered == self.full[None, :]).all(axis=1)).tolist():
                found.append(sum(1 << self.candidates[i] for i in combinations[hit].tolist()))
        return found

    def first(self, size: int, tries: int) -> int | None:
        """Mask of the first cover among the first ``tries`` size-combinations in lexicographic order."""
        done = 0
        for chunk in _combination_chunks(len(self.candidates), size):
            combinations = chunk[: tries - done]
            covered = np.bitwise_or.reduce(self.columns[combinations], axis=1)
            hits = (covered == self.full[None, :]).all(axis=1)
            if hits.any():
                return sum(1 << self.candidates[i] for i in combinations[int(np.argmax(hits))].tolist())
            done += combinations.shape[0]
            if done >= tries:
                break
        return None


def _combination_chunks(m: int, size: int) -> Iterator[npt.NDArray[np.intp]]:
    """Every size-combination of range(m) in lexicographic order, `CHUNK` rows at a time."""
    if math.comb(m, size) <= CHUNK:
        yield _small_combinations(m, size)
        return
    combinations = itertools.combinations(range(m), size)
    while True:
        flat = np.fromiter(
            itertools.chain.from_iterable(itertools.islice(combinations, CHUNK)), dtype=np.intp, count=-1
        )
        if flat.size == 0:
            return
        yield flat.reshape(-1, size)


@lru_cache(maxsize=512)
def _small_combinations(m: int, size: int) -> npt.NDArray[np.intp]:
    flat = np.fromiter(itertools.chain.from_iterable(itertools.combinations(range(m), size)), dtype=np.intp)
    return flat.reshape(-1, size)


# ---------------------------------------------------------------------------------------------------------
# HiGHS, when enumeration would take too long
# ---------------------------------------------------------------------------------------------------------


def _highs_lexicographic(rows: MaskArray, candidates: list[int], size: int) -> int:
    """Views fixed in ascending order, each kept while a cover of ``size`` views remains with it."""
    fixed: dict[int, int] = {}
    taken = 0
    for view in candidates:
        if taken < size and _min_cover_size(rows, candidates, {**fixed, view: 1}, exactly=size) == size:
            fixed[view], taken = 1, taken + 1
        else:
            fixed[view] = 0
    chosen = sum(1 << v for v, x in fixed.items() if x)
    if taken != size or not bool(((rows & np.uint64(chosen)) != 0).all()):
        raise SolverFailure("the tie-break by fixing views did not end on a cover of the minimum size")
    return chosen


def _min_cover_size(
    rows: MaskArray, candidates: list[int], fixed: dict[int, int], exactly: int | None = None
) -> int | None:
    """Fewest candidate views covering every row with some views fixed (None: no such cover).

    With ``exactly`` the view count is pinned and the model is a feasibility question.
    """
    m = len(candidates)
    incidence = ((rows[:, None] >> np.array(candidates, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(bool)
    starts = np.concatenate([[0], np.cumsum(incidence.sum(axis=1))]).astype(np.int32)
    columns = np.nonzero(incidence)[1].astype(np.int32)
    values = np.ones(columns.size)
    lower_rows, upper_rows = np.ones(rows.size), np.full(rows.size, highspy.kHighsInf)
    if exactly is not None:
        starts = np.append(starts, starts[-1] + m).astype(np.int32)
        columns = np.concatenate([columns, np.arange(m, dtype=np.int32)])
        values = np.concatenate([values, np.ones(m)])
        lower_rows, upper_rows = np.append(lower_rows, exactly), np.append(upper_rows, exactly)
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = m, lower_rows.size
    lp.col_cost_ = np.zeros(m) if exactly is not None else np.ones(m)
    lp.col_lower_ = np.array([1.0 if fixed.get(v) == 1 else 0.0 for v in candidates])
    lp.col_upper_ = np.array([0.0 if fixed.get(v) == 0 else 1.0 for v in candidates])
    lp.row_lower_, lp.row_upper_ = lower_rows, upper_rows
    lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
    lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = starts, columns, values
    lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = m, lower_rows.size
    lp.integrality_ = [highspy.HighsVarType.kInteger] * m
    # setcover's factory: HiGHS sizes one thread pool per process, and it keeps track of that size.
    with HIGHS_LOCK:  # shards are checked on a few threads; HiGHS's scheduler is one per process
        solver = setcover.highs_solver(1, TIME_LIMIT)
        solver.passModel(lp)
        solver.run()
    status = solver.getModelStatus()
    if status == highspy.HighsModelStatus.kInfeasible:
        return None
    if status != highspy.HighsModelStatus.kOptimal:
        raise SolverFailure(f"HiGHS: {solver.modelStatusToString(status)}")
    return round(sum(solver.getSolution().col_value))
