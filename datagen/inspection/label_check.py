"""The label checks of `datagen shards validate --all`: each objective's labels against a solve of our own.

`storage.validate` only asks whether a label keeps its objective's promise (a cover covers its U).
Here every checked label is judged by its objective's own checker (`LabelChecker`, named by
`schemas.objectives.Objective.checker`: `datagen.inspection.cover_check` for ``cover``,
`datagen.inspection.coverage_check` for the visibility objectives), found by other means than the
generator's solver, so a bug there cannot hide here; the index must hold the same label as the
shard, and a version-3 dataset's next-view labels are walked again (`datagen.inspection.next_view_check`).

This module is what every objective shares: the dataset and shard drivers (`check_labels`, and
`ShardLabelCheck` as `storage.validate`'s per-shard hook), the report (`LabelProblem` lines of the
kinds below), what a checker is given (`StoredSets`) and the tools the checkers share (the key masks
of P_full, the enumeration of view combinations, HiGHS's lock and time limit).
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

import numpy as np
import numpy.typing as npt

from datagen.pipeline import setcover
from schemas.config import GenerationConfig
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
)
from storage.dataset import index_rows_of, task_records

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
    (`storage.dataset.index_rows_of`: the manifest's row groups that hold them): the whole index as Python
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
# what a checker is given, and what the checkers share
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


class SolverFailure(Exception):
    """HiGHS did not prove its answer (time limit or error): the label is neither passed nor failed."""


def combination_chunks(m: int, size: int) -> Iterator[npt.NDArray[np.intp]]:
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
