"""Dataset statistics for ``shards stats``: read from the Parquet index and the commit and failure
records alone (no shard is opened), so they stay fast on tens of thousands of samples and any URL."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from datagen.inspection.listing import failed_tasks
from datagen.pipeline.step_timing import StepTotals, step_totals
from storage import Dataset, committed_tasks

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
    """`NextViewStats` from the index alone; None for a dataset without them."""
    index = dataset.index
    if "best_view" not in index.column_names:
        return None
    best = index.column("best_view").to_numpy().astype(np.int64)
    has_next = best >= 0
    ties = index.column("best_view_ties").to_numpy()[has_next]
    sizes = index.column("case_size").to_numpy()[has_next]
    visible = index.column("visible_size").to_numpy()[has_next].astype(np.float64)
    gains = index.column("best_gain").to_numpy()[has_next].astype(np.float64)
    share = np.divide(gains, visible, out=np.zeros_like(gains), where=visible > 0)
    groups = {str(int(size)): ties[sizes == size] for size in np.unique(sizes)} | {"all": ties}
    histogram, _ = np.histogram(share, bins=GAIN_BINS, range=(0.0, 1.0))
    return NextViewStats(
        unique={name: float(np.mean(found == 1)) for name, found in groups.items() if found.size},
        best_gain_share=percentiles(share),
        best_gain_histogram=[int(count) for count in histogram],
        best_view_counts={int(k): v for k, v in _sorted_counts(best[has_next].tolist()).items()},
        no_next_view=int(np.count_nonzero(~has_next)),
    )


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
    index = dataset.index
    labelled = ~index.column("empty_label").to_numpy(zero_copy_only=False)
    counts = index.column("min_covers").to_numpy()[labelled]
    sizes = index.column("case_size").to_numpy()[labelled]
    support = np.bitwise_count(index.column("label_support").to_numpy()[labelled]).astype(np.int64)
    groups = {str(int(size)): counts[sizes == size] for size in np.unique(sizes)} | {"all": counts}
    return LabelAmbiguityStats(
        unique={name: float(np.mean(found == 1)) for name, found in groups.items() if found.size},
        median_covers={name: float(np.median(found)) for name, found in groups.items() if found.size},
        capped=int(np.count_nonzero(~index.column("min_covers_exact").to_numpy(zero_copy_only=False)[labelled])),
        count_percentiles=percentiles(counts),
        support_size_percentiles=percentiles(support),
    )


def percentiles(values: npt.NDArray[Any]) -> dict[str, float | None]:
    """``{"p0": ..., "p100": ...}`` of `PERCENTILES`; None values for an empty array."""
    if values.size == 0:
        return {f"p{q}": None for q in PERCENTILES}
    found = np.percentile(values.astype(np.float64), PERCENTILES)
    return {f"p{q}": float(v) for q, v in zip(PERCENTILES, found, strict=True)}


def _sorted_counts(values: list[Any]) -> dict[Any, int]:
    return dict(sorted(Counter(values).items()))


def dataset_stats(dataset: Dataset) -> DatasetStats:
    """Statistics of every committed sample, plus the failed tasks (from the failure records)."""
    index = dataset.index
    objects = index.column("object_name").to_pylist()
    rotations = index.column("rotation").to_pylist()
    case_sizes = index.column("case_size").to_pylist()
    label_sizes = index.column("label_size").to_pylist()
    histogram: dict[int, dict[int, int]] = {}
    for (case_size, label_size), count in sorted(Counter(zip(case_sizes, label_sizes, strict=True)).items()):
        histogram.setdefault(int(case_size), {})[int(label_size)] = count
    points = index.column("num_points").to_numpy().astype(np.int64)
    seconds = index.column("solver_seconds").to_numpy().astype(np.float64)
    records = committed_tasks(dataset.location)
    committed = {record.task_id for record in records}
    return DatasetStats(
        url=dataset.url,
        samples=len(dataset),
        committed_tasks=len(committed),
        samples_per_object=_sorted_counts(objects),
        samples_per_task=[
            TaskCount(name, int(rotation), count)
            for (name, rotation), count in _sorted_counts(list(zip(objects, rotations, strict=True))).items()
        ],
        cases_per_case_size={int(k): v for k, v in _sorted_counts(case_sizes).items()},
        label_sizes=histogram,
        empty_labels=int(np.count_nonzero(index.column("empty_label").to_numpy(zero_copy_only=False))),
        points_percentiles=percentiles(points),
        solver_seconds_percentiles=percentiles(seconds),
        solver_proofs=_sorted_counts(index.column("solver_proof").to_pylist()),
        ambiguity=ambiguity_stats(dataset),
        failed=[FailedTask(t.task_id, t.object_name, t.origin, t.message) for t in failed_tasks(dataset, committed)],
        points_per_sample=points,
        solver_seconds=seconds,
        step_seconds=step_totals(records),
        objective=dataset.info.config.objective_text(),
        next_view=next_view_stats(dataset),
    )
