"""Dataset statistics for ``shards stats``: read from the Parquet index and the commit and failure
records alone (no shard is opened), so they stay fast on tens of thousands of samples and any URL."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from datagen.inspection.listing import failed_tasks
from datagen.pipeline.step_timing import StepTotals, step_totals
from storage import Dataset

PERCENTILES = (0, 5, 50, 95, 100)
"""The percentiles reported for per-sample quantities (numpy's default linear interpolation)."""


@dataclass(frozen=True)
class TaskCount:
    """Samples of one (object, rotation)."""

    object_name: str
    rotation: int
    samples: int


@dataclass(frozen=True)
class FailedTask:
    task_id: str
    object_name: str
    origin: str
    message: str


@dataclass(frozen=True)
class DatasetStats:
    """What a dataset holds, summarised; `to_json` gives the machine-readable form."""

    url: str
    samples: int
    committed_tasks: int
    samples_per_object: dict[str, int]
    """By object name, sorted."""
    samples_per_task: list[TaskCount]
    """By (object name, rotation), sorted."""
    cases_per_case_size: dict[int, int]
    """Number of input views |S| -> samples."""
    label_sizes: dict[int, dict[int, int]]
    """Case size -> label size |L| -> samples (the label-size histogram per case size)."""
    empty_labels: int
    points_percentiles: dict[str, float | None]
    """``p0``...``p100`` of the refined cloud size per sample (None without samples)."""
    solver_seconds_percentiles: dict[str, float | None]
    """``p0``...``p100`` of the labelling time per sample, empty labels included."""
    solver_proofs: dict[str, int]
    """How each label was proven optimal ('none' for an empty label) -> samples."""
    ambiguity: LabelAmbiguityStats | None
    """How many minimum covers the labels were chosen from (None for a version-1 dataset)."""
    failed: list[FailedTask]
    points_per_sample: npt.NDArray[np.int64] = field(repr=False, compare=False)
    """The raw values behind the percentiles, for the histograms (not in `to_json`)."""
    solver_seconds: npt.NDArray[np.float64] = field(repr=False, compare=False)
    step_seconds: StepTotals = field(default_factory=lambda: StepTotals(tasks=0, untimed=0))
    """CPU and wall seconds per task step summed over the commit records that carry them."""
    objective: str = "cover"
    """What the labels are (`GenerationConfig.objective_text`: the objective and its parameter)."""
    next_view: NextViewStats | None = None
    """The next-view labels (None before schema version 3)."""

    def to_json(self) -> dict[str, Any]:
        """Plain dicts, lists and numbers (integer keys written as strings, as JSON requires)."""
        return {
            "url": self.url,
            "objective": self.objective,
            "samples": self.samples,
            "committed_tasks": self.committed_tasks,
            "failed_tasks": len(self.failed),
            "samples_per_object": dict(self.samples_per_object),
            "samples_per_task": [
                {"object": t.object_name, "rotation": t.rotation, "samples": t.samples} for t in self.samples_per_task
            ],
            "cases_per_case_size": {str(k): v for k, v in self.cases_per_case_size.items()},
            "label_sizes": {
                str(size): {str(k): v for k, v in histogram.items()} for size, histogram in self.label_sizes.items()
            },
            "empty_labels": self.empty_labels,
            "points_percentiles": dict(self.points_percentiles),
            "solver_seconds_percentiles": dict(self.solver_seconds_percentiles),
            "solver_proofs": dict(self.solver_proofs),
            "ambiguity": None if self.ambiguity is None else self.ambiguity.to_json(),
            "failed": [
                {"task_id": f.task_id, "object": f.object_name, "origin": f.origin, "message": f.message}
                for f in self.failed
            ],
            "step_seconds": self.step_seconds.to_json() if self.step_seconds.tasks else None,
            "next_view": None if self.next_view is None else self.next_view.to_json(),
        }


GAIN_BINS = 10
"""Bins of the best-gain histogram over [0, 1] (the best view's share of what any view sees)."""


@dataclass(frozen=True)
class NextViewStats:
    """The next-view labels (version 3) from the index: how often the best next view is unique, how
    much it adds, and which views are best how often."""

    unique: dict[str, float]
    """Case size (and ``all``) -> share of samples with a next view whose best view is unique."""
    best_gain_share: dict[str, float | None]
    """Percentiles of the best view's gain over the keys any view sees."""
    best_gain_histogram: list[int]
    """Samples per `GAIN_BINS` equal bins of that share over [0, 1]."""
    best_view_counts: dict[int, int]
    """View -> samples whose best next view it is (sorted by view)."""
    no_next_view: int
    """Samples whose case has every view."""

    def to_json(self) -> dict[str, Any]:
        return {
            "unique": dict(self.unique),
            "best_gain_share": dict(self.best_gain_share),
            "best_gain_histogram": list(self.best_gain_histogram),
            "best_view_counts": {str(k): v for k, v in self.best_view_counts.items()},
            "no_next_view": self.no_next_view,
        }


def next_view_stats(dataset: Dataset) -> NextViewStats | None:
    """`NextViewStats` from the index alone; None for a dataset without them. Columns read once and not
    kept, one per-size group at a time: a few columns of millions at the peak."""
    if "best_view" not in dataset.samples.column_names:
        return None
    best = dataset.values("best_view", keep=False)
    has_next = best >= 0
    best_view_counts = _counts(best[has_next])
    del best
    ties = dataset.values("best_view_ties", keep=False)[has_next]
    sizes = dataset.values("case_size")[has_next]
    share = dataset.values("best_gain", keep=False)[has_next].astype(np.float64)
    visible = dataset.values("visible_size", keep=False)[has_next]
    np.divide(share, visible, out=share, where=visible > 0)
    share[visible <= 0] = 0.0
    del visible
    histogram, _ = np.histogram(share, bins=GAIN_BINS, range=(0.0, 1.0))
    return NextViewStats(
        unique=_by_size(sizes, ties, lambda found: float(np.mean(found == 1))),
        best_gain_share=percentiles(share),
        best_gain_histogram=[int(count) for count in histogram],
        best_view_counts=best_view_counts,
        no_next_view=int(np.count_nonzero(~has_next)),
    )


def _by_size(sizes: npt.NDArray[Any], values: npt.NDArray[Any], statistic: Callable[[Any], float]) -> dict[str, float]:
    """``statistic`` of ``values`` per case size (str keys, ascending) and of all of them (``all``),
    each size's values gathered in turn."""
    found = {str(int(size)): statistic(values[sizes == size]) for size in np.unique(sizes)}
    return found | ({"all": statistic(values)} if values.size else {})


@dataclass(frozen=True)
class LabelAmbiguityStats:
    """The labels' ambiguity (version 2): how often the minimum cover is unique, how many there are,
    how many views could take part, by case size and overall."""

    unique: dict[str, float]
    """Case size (and ``all``) -> share of non-empty labels with exactly one minimum cover."""
    median_covers: dict[str, float]
    """Case size (and ``all``) -> median count of minimum covers of the non-empty labels."""
    capped: int
    """Labels whose count is a lower bound (more minimum covers than the config's cap)."""
    count_percentiles: dict[str, float | None]
    support_size_percentiles: dict[str, float | None]
    """Views in any minimum cover, per non-empty label."""

    def to_json(self) -> dict[str, Any]:
        return {
            "unique": dict(self.unique),
            "median_covers": dict(self.median_covers),
            "capped": self.capped,
            "count_percentiles": dict(self.count_percentiles),
            "support_size_percentiles": dict(self.support_size_percentiles),
        }


def ambiguity_stats(dataset: Dataset) -> LabelAmbiguityStats | None:
    """`LabelAmbiguityStats` from the index alone; None for a dataset without them."""
    if not dataset.has_ambiguity:
        return None
    labelled = dataset.values("empty_label", keep=False) == 0
    counts = dataset.values("min_covers", keep=False)[labelled]
    sizes = dataset.values("case_size")[labelled]
    support = np.bitwise_count(dataset.values("label_support", keep=False)[labelled])
    capped = int(np.count_nonzero(dataset.values("min_covers_exact", keep=False)[labelled] == 0))
    return LabelAmbiguityStats(
        unique=_by_size(sizes, counts, lambda found: float(np.mean(found == 1))),
        median_covers=_by_size(sizes, counts, lambda found: float(np.median(found))),
        capped=capped,
        count_percentiles=percentiles(counts),
        support_size_percentiles=percentiles(support),
    )


def percentiles(values: npt.NDArray[Any]) -> dict[str, float | None]:
    """``{"p0": ..., "p100": ...}`` of `PERCENTILES`; None values for an empty array."""
    if values.size == 0:
        return {f"p{q}": None for q in PERCENTILES}
    found = np.percentile(values.astype(np.float64), PERCENTILES)
    return {f"p{q}": float(v) for q, v in zip(PERCENTILES, found, strict=True)}


def _counts(values: npt.NDArray[Any]) -> dict[int, int]:
    """Samples per value of an integer column, sorted by value."""
    found, counts = np.unique(values, return_counts=True)
    return {int(v): int(c) for v, c in zip(found.tolist(), counts.tolist(), strict=True)}


def _per_task(dataset: Dataset) -> list[TaskCount]:
    """Samples per (object name, rotation), sorted: from the manifest's tasks table when it names every
    task's object, else counted over the index columns."""
    tasks = dataset.task_table()
    if tasks is not None and _names_every_object(tasks) and dataset.samples.positions is None:
        table = tasks.filter(pc.greater(tasks.column("num_samples"), 0)).select(
            ["object_name", "rotation", "num_samples"]
        )
        grouped = table.group_by(["object_name", "rotation"], use_threads=False).aggregate([("num_samples", "sum")])
        columns = ("object_name", "rotation", "num_samples_sum")
    else:
        table = pa.table({"object_name": dataset.column("object_name"), "rotation": dataset.column("rotation")})
        grouped = table.group_by(["object_name", "rotation"], use_threads=False).aggregate([("rotation", "count")])
        columns = ("object_name", "rotation", "rotation_count")
    rows = zip(*(grouped.column(c).to_pylist() for c in columns), strict=True)
    return [TaskCount(name, int(rotation), int(count)) for name, rotation, count in sorted(rows)]


def _names_every_object(tasks: pa.Table) -> bool:
    """Whether every task with samples names its object (a manifest written before the table held them
    does not)."""
    with_samples = tasks.filter(pc.greater(tasks.column("num_samples"), 0))
    return with_samples.column("object_name").null_count == 0


def _per_object(dataset: Dataset, per_task: list[TaskCount]) -> dict[str, int]:
    """Samples per object name, sorted."""
    counts: dict[str, int] = {}
    for task in per_task:
        counts[task.object_name] = counts.get(task.object_name, 0) + task.samples
    return dict(sorted(counts.items()))


def dataset_stats(dataset: Dataset) -> DatasetStats:
    """Statistics of every committed sample, plus the failed tasks (from the failure records). Column by
    column, counted in numpy and pyarrow: about a second a million samples, a few columns in memory."""
    case_sizes = dataset.values("case_size")
    label_sizes = dataset.values("label_size")
    histogram: dict[int, dict[int, int]] = {}
    width = int(label_sizes.max(initial=0)) + 1  # one count per (case size, label size), no sort of millions
    pairs = np.bincount(case_sizes.astype(np.int64) * width + label_sizes, minlength=width)
    for key in np.flatnonzero(pairs).tolist():
        histogram.setdefault(key // width, {})[key % width] = int(pairs[key])
    points = dataset.values("num_points")
    seconds = dataset.values("solver_seconds")
    records = dataset.task_records()
    committed = {record.task_id for record in records}
    per_task = _per_task(dataset)
    return DatasetStats(
        url=dataset.url,
        samples=len(dataset),
        committed_tasks=len(committed),
        samples_per_object=_per_object(dataset, per_task),
        samples_per_task=per_task,
        cases_per_case_size={size: sum(labels.values()) for size, labels in histogram.items()},
        label_sizes=histogram,
        empty_labels=int(np.count_nonzero(dataset.values("empty_label"))),
        points_percentiles=percentiles(points),
        solver_seconds_percentiles=percentiles(seconds),
        solver_proofs=dataset.counts("solver_proof"),
        ambiguity=ambiguity_stats(dataset),
        failed=[FailedTask(t.task_id, t.object_name, t.origin, t.message) for t in failed_tasks(dataset, committed)],
        points_per_sample=points,
        solver_seconds=seconds,
        step_seconds=step_totals(records),
        objective=dataset.info.config.objective_text(),
        next_view=next_view_stats(dataset),
    )
