"""`validate`: check a dataset's structure and that every checked label covers its U (numpy only).

Minimality and the lexicographic tie-break need a solver; ``datagen shards validate --all`` adds
them on top of this. Each problem is one line naming the shard (or file) and, where it applies,
the row.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.index import CommitRecord
from schemas.shard import (
    COVER_ROWS,
    COVERAGE_GAINS,
    COVERS,
    GAIN_DTYPE,
    GAIN_TOTALS,
    GRID_FRAME,
    GRID_HITS,
    GRID_MISSES,
    GT_KEYS,
    KEY_DTYPE,
    KEY_SETS,
    LABEL_COLUMN,
    MASK_DTYPE,
    MASKS,
    OFFSET_DTYPE,
    TASK_SETS,
    VIEW_GAINS,
    VIEW_STATE_COLUMN,
    ShardAttributes,
    array_names,
    keys_array,
    offsets_array,
    ordered_points,
    point_order,
)
from storage.checks.file_checks import check_failures, check_finalised_index, check_fragments, leftover_temporaries
from storage.dataset.info import read_info
from storage.dataset.manifest import TaskRecords, task_records
from storage.dataset.problems import Mend, Problem, lines
from storage.dataset.sample_index import numpy_of
from storage.samples.covers import undominated, universe_rows
from storage.samples.gains import MaskCounts
from storage.samples.label_judges import JudgedTask, LabelJudge, task_judge
from storage.samples.occupancy_grid import PACKED_CELLS
from storage.samples.visibility import key_view_masks
from storage.shards.groups import ShardReader
from storage.store.errors import check_store
from storage.store.location import DamagedFile, Location, StorageError, open_location

SAMPLED_ROWS_PER_SHARD = 8
SHARD_THREADS = 8
SAMPLE_STREAM = 11
"""The purpose number of the stream that draws a sampled validation's tasks."""


@dataclass(frozen=True)
class _Shard:
    """Problems of one committed shard: re-running its task mends them."""

    record: CommitRecord

    def __call__(self, kind: str, message: str, array: str | None = None, place: str = "") -> Problem:
        return Problem(kind, self.record.shard, message, Mend.TASK, self.record.task_id, array, place)


ShardCheck = Callable[[CommitRecord, ShardReader], None]
"""An extra check run on each structurally sound shard while its arrays are cached (so a caller such
as the solver-based label check reads every shard once); it records its own findings. Called from
worker threads."""


@dataclass(frozen=True)
class Validation:
    """What `validate_dataset` found: ``problems`` (the dataset is not sound; readers refuse it or
    part of it) and ``warnings`` (harmless leftovers a user may clean up)."""

    problems: list[Problem] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    tasks_checked: int = 0
    """Tasks whose shard (and fragment) were read and checked: all of them, or a ``sample`` of them."""
    tasks_total: int = 0

    @property
    def lines(self) -> list[str]:
        """The problems as printed."""
        return lines(self.problems)


def validate(
    url: str,
    full: bool = False,
    seed: int = 0,
    storage_options: dict[str, Any] | None = None,
    shard_check: ShardCheck | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[str]:
    """Every problem found, one printed line each (empty when the dataset is sound; the records and the
    warnings about leftovers: `validate_dataset`).

    ``full=False`` checks coverage on a seeded sample of rows per shard; ``full=True`` on every row.
    ``progress`` is called with (shards done, shards in all).
    """
    return validate_dataset(url, full, seed, storage_options, shard_check, progress).lines


def validate_dataset(
    url: str,
    full: bool = False,
    seed: int = 0,
    storage_options: dict[str, Any] | None = None,
    shard_check: ShardCheck | None = None,
    progress: Callable[[int, int], None] | None = None,
    sample: float | None = None,
) -> Validation:
    """`validate`'s problems as records (`storage.dataset.Problem`) plus warnings; never raises for a
    damaged file (each is a problem); an unreachable store is `StoreUnreachable`.

    ``sample`` (0 < sample <= 1): read and check the shards and index fragments of that share of the
    tasks only (at least one, drawn from ``seed``); every record, the finalised index and the failure
    records are still checked whole. The result says how many tasks were checked. The same checks in
    parts (`plan_validation`, `check_dataset`, `check_tasks`) run side by side: `datagen shards validate`
    spreads `check_tasks` over Ray."""
    plan = plan_validation(url, storage_options, sample, seed)
    found = check_dataset(plan)
    if plan.info is not None:
        problems = check_tasks(
            plan.location, plan.info, plan.chosen, plan.numbers, plan.tasks.spans, full, seed, shard_check, progress
        )
        found.problems.extend(problems)
    return found


@dataclass(frozen=True)
class ValidationPlan:
    """What a validation reads, decided once: the dataset, its tasks and those whose files are read."""

    location: Location
    info: DatasetInfo | None
    """None when ``dataset.json`` cannot be read (a problem): the shards are not checked then."""
    tasks: TaskRecords
    chosen: list[CommitRecord]
    """The tasks whose shard (and fragment) are read: all, or a sample."""
    problems: list[Problem]
    """What reading the plan itself found (``dataset.json``, records)."""
    absent: bool = False
    """No dataset at all at the location (``problems`` says so): nothing else is checked."""

    @property
    def numbers(self) -> dict[str, int]:
        """Each task's place among all tasks: its rows' sampling stream, whoever checks it."""
        return {record.task_id: number for number, record in enumerate(self.tasks.records)}


def plan_validation(
    url: str, storage_options: dict[str, Any] | None = None, sample: float | None = None, seed: int = 0
) -> ValidationPlan:
    """Read ``dataset.json`` and every task's record, and choose the tasks whose files are read."""
    if sample is not None and not 0 < sample <= 1:
        raise StorageError(f"--sample {sample}: give a share of the tasks between 0 and 1 (0.01 checks 1 %)")
    location = open_location(url, storage_options)
    check_store(location)  # an unreachable store is an error, not a problem of the dataset
    problems: list[Problem] = []
    try:
        info: DatasetInfo | None = read_info(location)
    except DamagedFile as exc:  # the records can still be checked; the shards need the config
        info = None
        problems.append(Problem("dataset", exc.relative, exc.problem, Mend.NONE))
    except StorageError as exc:  # no dataset here at all
        nothing = TaskRecords([], [], {})
        return ValidationPlan(location, None, nothing, [], [Problem("dataset", "", str(exc), Mend.NONE)], absent=True)
    tasks = task_records(location)
    chosen = sampled_tasks(tasks.records, sample, seed)
    return ValidationPlan(location, info, tasks, chosen, [*problems, *tasks.problems])


def check_dataset(plan: ValidationPlan) -> Validation:
    """The checks of the whole dataset: the finalised index against the records, row by row, the
    failure records and leftovers (``plan.chosen``'s folders only when a sample), and, where no finalised
    index covers the records, the chosen tasks' fragments (the index readers merge then)."""
    location, commits, chosen = plan.location, plan.tasks.records, plan.chosen
    found = Validation(problems=list(plan.problems))
    if plan.absent:
        return found
    version = None if plan.info is None else plan.info.schema_version
    found.problems.extend(_check_index(location, commits, version, bool(plan.tasks.spans), chosen))
    failure_problems, stale = check_failures(location, commits)
    found.problems.extend(failure_problems)
    sampled = None if len(chosen) == len(commits) else [record.task_id for record in chosen]
    found.warnings.extend(stale + leftover_temporaries(location, sampled))
    return replace(found, tasks_checked=len(chosen), tasks_total=len(commits))


def check_tasks(
    location: Location,
    info: DatasetInfo,
    records: list[CommitRecord],
    numbers: dict[str, int],
    spans: dict[str, tuple[str, int, int]],
    full: bool,
    seed: int,
    shard_check: ShardCheck | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Problem]:
    """Each of ``records``' shards (side by side on threads), with ``shard_check`` run on each sound
    one. ``numbers``: each task's place among all the dataset's tasks (its rows' sampling stream);
    ``spans``: where a packed dataset's shards lie. What a worker of a parallel validation runs."""
    tasks = TaskRecords(records, [], spans)
    return _check_shards(location, info, tasks, records, full, seed, shard_check, progress, numbers)


def sampled_tasks(records: list[CommitRecord], sample: float | None, seed: int) -> list[CommitRecord]:
    """Every record, or a seeded share ``sample`` of them (at least one), in task order."""
    if sample is None or sample >= 1 or not records:
        return list(records)
    count = max(1, math.ceil(sample * len(records)))
    chosen = np.random.default_rng(np.random.SeedSequence([seed, SAMPLE_STREAM])).choice(
        len(records), count, replace=False
    )
    return [records[i] for i in sorted(chosen.tolist())]


def _check_shards(
    location: Location,
    info: DatasetInfo,
    tasks: TaskRecords,
    commits: list[CommitRecord],
    full: bool,
    seed: int,
    shard_check: ShardCheck | None,
    progress: Callable[[int, int], None] | None,
    numbers: dict[str, int],
) -> list[Problem]:
    """The shards of ``commits`` (all tasks, or a sample of them), side by side."""
    problems: list[Problem] = []
    num_views, config = info.num_views, info.config

    def check(record: CommitRecord) -> list[Problem]:
        # one stream per shard, numbered in the whole dataset: threads and sampling cannot reorder draws
        rng = np.random.default_rng([seed, numbers[record.task_id]])
        span = tasks.spans.get(record.shard)
        return list(
            _check_shard(location, record, info.schema_version, num_views, config, full, rng, shard_check, span)
        )

    # Shards are checked side by side: a shard costs ~40 small zarr reads whose latency (an event
    # loop round trip locally, a request on an object store) overlaps across threads.
    with ThreadPoolExecutor(max_workers=SHARD_THREADS) as pool:
        for done, shard_problems in enumerate(pool.map(check, commits), start=1):
            problems.extend(shard_problems)
            if progress:
                progress(done, len(commits))
    return problems


def _check_shard(
    location: Location,
    record: CommitRecord,
    schema_version: int,
    num_views: int,
    config: GenerationConfig,
    full: bool,
    rng: np.random.Generator,
    shard_check: ShardCheck | None = None,
    span: tuple[str, int, int] | None = None,
) -> Iterator[Problem]:
    at = _Shard(record)
    try:  # verified below: each finding becomes a problem
        shard = ShardReader(location, record.shard, verify=False, span=span)
    except DamagedFile as exc:  # a missing or unreadable group: report, keep checking others
        yield at("shard", f"cannot open shard ({exc.problem})")
        return
    try:
        yield from _check_open_shard(shard, record, schema_version, num_views, config, full, rng, shard_check)
    except DamagedFile as exc:  # unreadable metadata of an array: the shard's last problem
        yield Problem("array", exc.relative, exc.problem, Mend.TASK, record.task_id)


def _check_open_shard(
    shard: ShardReader,
    record: CommitRecord,
    schema_version: int,
    num_views: int,
    config: GenerationConfig,
    full: bool,
    rng: np.random.Generator,
    shard_check: ShardCheck | None,
) -> Iterator[Problem]:
    at = _Shard(record)
    count = record.num_samples
    if shard.attributes.num_samples != count or shard.attributes.attempt_id != record.attempt_id:
        yield at("shard", "attributes disagree with the commit record (samples or attempt id)")
    if shard.attributes.schema_version != schema_version:
        found = shard.attributes.schema_version
        yield at("shard", f"schema version {found}, the dataset is version {schema_version}")
        return
    expected = array_names(schema_version)
    names = shard.array_names()
    missing = sorted(set(expected) - set(names))
    if missing:
        yield at("array", f"missing arrays {missing}")
        return
    incomplete = shard.incomplete_arrays(expected)
    if incomplete:
        yield at("array", f"arrays with missing chunks {incomplete}; the shard is truncated")
        return
    try:
        arrays = {name: shard.array(name) for name in expected}
    except DamagedFile as exc:
        yield at("array", f"cannot read arrays ({exc.relative}: {exc.problem})")
        return
    masks = arrays[MASKS]
    if masks.dtype != MASK_DTYPE or masks.shape != (count, 2):
        yield at("array", f"masks has shape {masks.shape} {masks.dtype}, expected ({count}, 2) uint64", MASKS)
        return
    shape_problems = list(_check_key_sets(at, arrays, count, num_views))
    yield from shape_problems
    if shape_problems:
        return
    unordered = {}
    if ordered_points(schema_version, "points"):
        unordered = _in_sorted_order(arrays, shard.attributes, config.seed)
    yield from _check_sorted_sets(at, {**arrays, **unordered}, per_sample=True, reordered=bool(unordered))
    yield from _check_sorted_sets(at, arrays, per_sample=False)
    too_wide = (masks >> np.uint64(num_views)) != 0 if num_views < 64 else np.zeros_like(masks, dtype=bool)
    for row in np.flatnonzero(too_wide.any(axis=1)):
        yield at("sample", f"mask has bits beyond the {num_views} views", MASKS, f"row {row}")
    overlap = (masks[:, VIEW_STATE_COLUMN] & masks[:, LABEL_COLUMN]) != 0
    for row in np.flatnonzero(overlap):
        yield at("sample", "label shares views with the input case", MASKS, f"row {row}")
    rows = np.arange(count) if full else np.sort(rng.permutation(count)[:SAMPLED_ROWS_PER_SHARD])
    full_masks = _full_masks(arrays, num_views, config.alpha)
    judge = task_judge(JudgedTask(full_masks, lambda: _task_sets(arrays, "visible", num_views), config))
    yield from _check_labels(at, masks, judge, rows)
    if schema_version >= 2:
        yield from _check_covers(at, arrays, count, full_masks, rows, judge.ties_problem)
    if schema_version >= 3:
        yield from _check_next_view(at, arrays, count, num_views, full_masks, rows)
    if shard_check is not None:
        shard_check(record, shard)


def _check_key_sets(at: _Shard, arrays: dict[str, npt.NDArray[Any]], count: int, num_views: int) -> Iterator[Problem]:
    expected = {name: count + 1 for name in KEY_SETS} | {name: num_views + 1 for name in TASK_SETS}
    for name, length in expected.items():
        keys, offsets = arrays[keys_array(name)], arrays[offsets_array(name)]
        if keys.dtype != KEY_DTYPE or keys.ndim != 2 or keys.shape[1] != 3:
            found = f"{keys.shape} {keys.dtype}"
            yield at("array", f"{keys_array(name)} has shape {found}, expected (K, 3) int16", keys_array(name))
            continue
        if offsets.dtype != OFFSET_DTYPE or offsets.shape != (length,):
            shape = f"{offsets.shape} {offsets.dtype}"
            message = f"{offsets_array(name)} has shape {shape}, expected ({length},) int64"
            yield at("array", message, offsets_array(name))
            continue
        if offsets[0] != 0 or (np.diff(offsets) < 0).any() or offsets[-1] != keys.shape[0]:
            bad = np.flatnonzero(np.diff(offsets) < 0)
            message = (
                f"{offsets_array(name)} not monotone from 0 to {keys.shape[0]} "
                f"(first {int(offsets[0])}, last {int(offsets[-1])}); the array is truncated or the offsets are bad"
            )
            yield at("array", message, offsets_array(name), f"row {int(bad[0])}" if bad.size else "")
    gt = arrays[GT_KEYS]
    if gt.dtype != KEY_DTYPE or gt.ndim != 2 or gt.shape[1] != 3:
        yield at("array", f"{GT_KEYS} has shape {gt.shape} {gt.dtype}, expected (G, 3) int16", GT_KEYS)
    elif (np.diff(_packed(gt)) <= 0).any():
        yield at("array", f"{GT_KEYS} is not sorted and unique", GT_KEYS)


def _in_sorted_order(
    arrays: dict[str, npt.NDArray[Any]], attributes: ShardAttributes, seed: int
) -> dict[str, npt.NDArray[Any]]:
    """A version-4 ``points_keys`` with each cloud put back from `schemas.shard.point_order` into the
    order it was drawn from, which must be sorted and unique: so the one check finds a cloud whose set
    or whose order departs from the rule."""
    name = keys_array("points")
    keys, offsets = arrays[name], arrays[offsets_array("points")]
    cases = arrays[MASKS][:, VIEW_STATE_COLUMN].tolist()
    back = np.empty_like(keys)
    for row, case in enumerate(cases):
        start, stop = int(offsets[row]), int(offsets[row + 1])
        order = point_order(seed, attributes.object_id, attributes.rotation, int(case), stop - start)
        back[start + order] = keys[start:stop]
    return {name: back}


def _check_sorted_sets(
    at: _Shard, arrays: dict[str, npt.NDArray[Any]], per_sample: bool, reordered: bool = False
) -> Iterator[Problem]:
    """Every key set is sorted (x, y, z) and unique: packed values strictly increase in a segment
    (``reordered``: the version-4 clouds once put back from their stored order)."""
    for name in KEY_SETS if per_sample else TASK_SETS:
        keys, offsets = arrays[keys_array(name)], arrays[offsets_array(name)]
        if keys.shape[0] < 2:
            continue
        rising = np.diff(_packed(keys)) > 0
        starts = offsets[1:-1]
        rising[starts[(starts > 0) & (starts < keys.shape[0])] - 1] = True  # segment boundaries
        if not rising.all():
            position = int(np.flatnonzero(~rising)[0]) + 1
            row = int(np.searchsorted(offsets, position, side="right")) - 1
            place = f"{'row' if per_sample else 'view'} {row}"
            message = f"{keys_array(name)} is not sorted and unique (zeroed or corrupt data)"
            if reordered and name == "points":
                message = (
                    f"{keys_array(name)} is not a sorted, unique set in the stored point order "
                    "(zeroed, corrupt or reordered data)"
                )
            yield at("array", message, keys_array(name), place)


def _packed(keys: npt.NDArray[np.int16]) -> npt.NDArray[np.int64]:
    k = keys.astype(np.int64) + (1 << 15)
    return (k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2]


def _task_sets(arrays: dict[str, npt.NDArray[Any]], name: str, num_views: int) -> list[npt.NDArray[np.int64]]:
    """A per-view key set family of the task (``visible`` or ``refined``) as packed keys."""
    keys, offsets = arrays[keys_array(name)], arrays[offsets_array(name)]
    return [_packed(keys[offsets[v] : offsets[v + 1]]) for v in range(num_views)]


def _full_masks(arrays: dict[str, npt.NDArray[Any]], num_views: int, alpha: int) -> npt.NDArray[np.uint64]:
    """P_full's masks recomputed from the stored P_i: each key's views, kept when at least alpha."""
    key_masks = key_view_masks(_task_sets(arrays, "refined", num_views))
    return key_masks[np.bitwise_count(key_masks) >= alpha]


def _check_labels(
    at: _Shard, masks: npt.NDArray[np.uint64], judge: LabelJudge, rows: npt.NDArray[np.int64]
) -> Iterator[Problem]:
    """Each checked row's label keeps its objective's promise (`storage.samples.label_judges`)."""
    for row in rows.tolist():
        problem = judge.label_problem(int(masks[row, VIEW_STATE_COLUMN]), int(masks[row, LABEL_COLUMN]))
        if problem:
            yield at(judge.problem_kind, problem, MASKS, f"row {row}")


TiesProblem = Callable[[npt.NDArray[np.uint64], int, int, npt.NDArray[np.uint64]], str | None]
"""(listed covers, case, label, the case's set-cover rows) -> what is wrong with the listed covers."""


def _check_covers(
    at: _Shard,
    arrays: dict[str, npt.NDArray[Any]],
    count: int,
    full_masks: npt.NDArray[np.uint64],
    rows: npt.NDArray[np.int64],
    ties_problem: TiesProblem,
) -> Iterator[Problem]:
    """Version 2: the cover rows are P_full's undominated masks, and each checked row lists the sets as
    good as its label (for the paper's objective: distinct covers of U, sorted, all of the label's
    size, the label among them). That they are the best and all of them needs a solver: `datagen shards
    validate --all`."""
    cover_rows, covers, offsets = arrays[COVER_ROWS], arrays[COVERS], arrays[offsets_array(COVERS)]
    for name, array in ((COVER_ROWS, cover_rows), (COVERS, covers)):
        if array.dtype != MASK_DTYPE or array.ndim != 1:
            yield at("array", f"{name} has shape {array.shape} {array.dtype}, expected (M,) uint64", name)
            return
    covers_offsets = offsets_array(COVERS)
    if offsets.dtype != OFFSET_DTYPE or offsets.shape != (count + 1,):
        found = f"{offsets.shape} {offsets.dtype}"
        yield at("array", f"{covers_offsets} has shape {found}, expected ({count + 1},) int64", covers_offsets)
        return
    if offsets[0] != 0 or (np.diff(offsets) < 0).any() or offsets[-1] != covers.size:
        message = f"{covers_offsets} not monotone from 0 to {covers.size}; the array is truncated"
        yield at("array", message, covers_offsets)
        return
    if not np.array_equal(cover_rows, undominated(full_masks)):
        message = f"{COVER_ROWS} are not the undominated masks of P_full recomputed from the stored P_i"
        yield at("array", message, COVER_ROWS)
        return
    masks = arrays[MASKS]
    for row in rows.tolist():
        case, label = int(masks[row, VIEW_STATE_COLUMN]), int(masks[row, LABEL_COLUMN])
        listed = covers[offsets[row] : offsets[row + 1]]
        problem = ties_problem(listed, case, label, universe_rows(cover_rows, case))
        if problem:
            yield at("covers", problem, COVERS, f"row {row}")


def _check_next_view(
    at: _Shard,
    arrays: dict[str, npt.NDArray[Any]],
    count: int,
    num_views: int,
    full_masks: npt.NDArray[np.uint64],
    rows: npt.NDArray[np.int64],
) -> Iterator[Problem]:
    """Version 3: the arrays' shapes, both denominators, and each checked row's gains recounted from
    the stored V_i and P_full. The grid's ray cells need the ray walk: `datagen shards validate --all`."""
    expected = {
        VIEW_GAINS: ((count, num_views), GAIN_DTYPE),
        COVERAGE_GAINS: ((count, num_views), GAIN_DTYPE),
        GAIN_TOTALS: ((2,), np.dtype(np.uint64)),
        GRID_FRAME: ((4,), np.dtype(np.float64)),
        GRID_HITS: ((num_views, PACKED_CELLS), np.dtype(np.uint8)),
        GRID_MISSES: ((num_views, PACKED_CELLS), np.dtype(np.uint8)),
    }
    bad = False
    for name, (shape, dtype) in expected.items():
        array = arrays[name]
        if array.shape != shape or array.dtype != dtype:
            yield at("array", f"{name} has shape {array.shape} {array.dtype}, expected {shape} {dtype}", name)
            bad = True
    if bad:
        return
    frame = arrays[GRID_FRAME]
    if not (np.isfinite(frame).all() and frame[3] > 0):
        yield at("array", f"{GRID_FRAME} is not a finite corner and a positive cell size", GRID_FRAME)
    if (np.unpackbits(arrays[GRID_HITS]) & np.unpackbits(arrays[GRID_MISSES])).any():
        yield at("array", f"a cell is in both {GRID_HITS} and {GRID_MISSES} of one view", GRID_HITS)
    seen = key_view_masks(_task_sets(arrays, "visible", num_views))
    totals = (int(seen.size), int(full_masks.size))
    if tuple(int(t) for t in arrays[GAIN_TOTALS]) != totals:
        stored = tuple(int(t) for t in arrays[GAIN_TOTALS])
        yield at("array", f"{GAIN_TOTALS} are {stored}, recounted {totals} (keys any view sees, |P_full|)", GAIN_TOTALS)
        return
    masks = arrays[MASKS]
    for name, key_masks in ((VIEW_GAINS, seen), (COVERAGE_GAINS, full_masks)):
        counted = MaskCounts.of(key_masks, num_views)
        for row in rows.tolist():
            if not np.array_equal(counted.gains(int(masks[row, VIEW_STATE_COLUMN])), arrays[name][row]):
                yield at("gains", f"{name} differ from the gains recounted from the stored sets", name, f"row {row}")


def _check_index(
    location: Location,
    commits: list[CommitRecord],
    schema_version: int | None,
    packed: bool = False,
    chosen: list[CommitRecord] | None = None,
) -> Iterator[Problem]:
    """The fragments (of the ``chosen`` tasks: all by default), the finalised index against the commit
    records, then each row of the index readers would use (the finalised one when it covers the commits,
    else the merged fragments). A packed dataset's fragments are copies of its samples table inside the
    packs: the table is checked."""
    checked = commits if chosen is None else chosen
    index_found, finalised = check_finalised_index(location, commits)
    keep = finalised is None  # the fragments' rows are checked only where readers would merge them
    found, fragments = check_fragments(location, checked, schema_version, keep) if not packed else ([], [])
    yield from found
    yield from index_found
    if finalised is not None:
        index = finalised
    elif fragments:
        index = pa.concat_tables(fragments)
    else:
        return
    yield from _duplicate_samples(index)
    yield from _rows_outside_their_shards(index, commits)


def _duplicate_samples(index: pa.Table) -> Iterator[Problem]:
    """A problem per index row whose sample id an earlier row holds (found by sorting, not by a set of
    millions of Python strings)."""
    ids = index.column("sample_id")
    order = pc.sort_indices(ids).to_numpy()  # stable: equal ids keep their index order
    ordered = ids.take(pa.array(order))
    same = pc.equal(ordered.slice(1), ordered.slice(0, max(len(ordered) - 1, 0)))
    again = np.flatnonzero(numpy_of(same).astype(bool)) + 1 if len(ordered) > 1 else np.zeros(0, np.int64)
    if not again.size:
        return
    first_of = np.arange(len(order))
    starts = np.ones(len(order), dtype=bool)
    starts[again] = False
    first_of = np.maximum.accumulate(np.where(starts, first_of, 0))
    shards, rows = index.column("shard"), numpy_of(index.column("row"))
    place = np.empty_like(order)
    place[order] = np.arange(len(order))
    for position in sorted(int(order[k]) for k in again.tolist()):
        first = int(order[first_of[place[position]]])
        sample, shard = ids[position].as_py(), shards[position].as_py()
        message = f"duplicate sample id {sample} (also {shards[first].as_py()} row {int(rows[first])})"
        yield Problem("index-row", shard, message, Mend.NONE, place=f"row {int(rows[position])}")


def _rows_outside_their_shards(index: pa.Table, commits: list[CommitRecord]) -> Iterator[Problem]:
    """A problem per index row naming a shard no commit record names, or a row outside its shard."""
    committed = {r.shard: r for r in commits}
    encoded = pc.dictionary_encode(index.column("shard")).combine_chunks()
    names = encoded.dictionary.to_pylist()
    codes = encoded.indices.to_numpy(zero_copy_only=False)
    counts = np.asarray([committed[n].num_samples if n in committed else -1 for n in names], dtype=np.int64)
    rows = numpy_of(index.column("row")).astype(np.int64)
    limit = counts[codes] if codes.size else np.zeros(0, dtype=np.int64)
    for position in np.flatnonzero((limit < 0) | (rows < 0) | (rows >= limit)).tolist():
        shard, row = names[int(codes[position])], int(rows[position])
        owner = committed.get(shard)
        if owner is None:
            message = f"points to {shard}, which no commit record names"
            yield Problem("index-row", "index", message, Mend.INDEX, place=f"row {position}")
        else:
            message = f"row {row} is outside {shard} ({owner.num_samples} samples)"
            yield Problem("index-row", "index", message, Mend.INDEX, owner.task_id, place=f"row {position}")
