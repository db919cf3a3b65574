"""One task in memory: (object, rotation) -> its labelled samples (docs/pipeline.md sections 1-8).

`run_task` composes the pure steps: scan (P_gt and the n observations), refine every single view,
filter to P_full and coverage masks, draw the long-tail cases from the visibility sets, refine
every multi-view case, label each case with its exact minimum cover, and add the next-best-view
labels (every view's gain, the best next view) and each view's cells of the occupancy grid. It also
returns the per-task sets (V_i, P_i, P_gt) that `relabel` needs to label the same cases for another
alpha without re-imaging or re-refining.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from datagen.pipeline.cases import long_tail_cases
from datagen.pipeline.coverage import Coverage, coverage_table, filter_to_ground_truth
from datagen.pipeline.imaging import Observation, TaskImaging
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.next_view import CaseGains, TaskGains
from datagen.pipeline.objectives import CaseLabeller, cover_solver, task_labeller
from datagen.pipeline.objects.prepare import PreparedObject
from datagen.pipeline.occupancy import ViewGrids, view_grids
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine.base import Refiner, RefineRequest, refined_keys
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.setcover import CoverResult, LabelError, SolverTimeLimit, TaskCover
from datagen.pipeline.step_timing import StepClock, timed
from datagen.pipeline.viewspace import ViewSpace
from schemas.config import GenerationConfig
from schemas.version import SCHEMA_VERSION

PackedKeys = npt.NDArray[np.int64]


@dataclass(frozen=True)
class TaskSets:
    """What a task keeps so that a new alpha can be labelled from storage alone."""

    visible: tuple[PackedKeys, ...]
    """V_i: keys each view saw."""
    refined: tuple[PackedKeys, ...]
    """P_i = P(O_i) intersected with P_gt."""
    ground_truth: PackedKeys
    """P_gt."""


@dataclass(frozen=True)
class Sample:
    """One labelled case of one task (a row of a shard)."""

    sample_id: str
    case: int
    """Mask of the input views S (view_state)."""
    label: int
    """Mask of the label views L."""
    points: PackedKeys
    """P(O_S): the refined cloud, the network input."""
    observed: PackedKeys
    """keys(O_S): what the input views saw."""
    full_size: int
    universe_size: int
    cover: CoverResult
    empty_label: bool
    gains: CaseGains | None = None
    """Every view's gain and the best next view (schema version 3)."""

    def point_centres(self, config: GenerationConfig) -> npt.NDArray[np.float32]:
        return key_centres(unpack_keys(self.points), config.voxel_size, config.grid_offset).astype(np.float32)


@dataclass(frozen=True)
class CaseFailure:
    case: int
    message: str


@dataclass(frozen=True)
class TaskResult:
    task_id: str
    object_id: str
    object_name: str
    rotation: int
    sets: TaskSets
    cases: tuple[int, ...]
    """Every drawn case, ordered by (size, mask), including dropped and failed ones."""
    samples: tuple[Sample, ...]
    failures: tuple[CaseFailure, ...]
    dropped_empty: int
    metadata: dict[str, object]
    """Per-sample metadata shared by every sample of the task (docs/pipeline.md section 8)."""
    cover_rows: npt.NDArray[np.uint64] = field(default_factory=lambda: np.empty(0, dtype=np.uint64))
    """The undominated masks of P_full: every case's set-cover rows are those its views miss."""
    seconds: dict[str, float] = field(default_factory=dict)
    """Coarse wall seconds (scan, refine, label); `run_task`'s clock has them per step."""
    grids: ViewGrids | None = None
    """Each view's cells of the occupancy grid (schema version 3)."""
    visible_size: int = 0
    """Keys any view sees: the visibility gains' denominator."""


def sample_id(task_id: str, case: int) -> str:
    return f"{task_id}-{case:016x}"


@dataclass(frozen=True)
class RefinedViews:
    """One task scanned and every single view refined: what labels and inputs are built from."""

    scan: TaskImaging
    refined: tuple[PackedKeys, ...]
    """P(O_i) for every view i: the network input of single-view case i."""
    sets: TaskSets


def refine_views(
    scan: TaskImaging, refiner: Refiner, config: GenerationConfig, object_id: str, rotation: int
) -> RefinedViews:
    """Refine every single view of a scanned task and keep the sets labels are computed from."""
    singles = list(scan.observations)
    single_refined = _refine(refiner, singles, config, object_id, rotation)
    sets = TaskSets(
        visible=tuple(o.keys for o in singles),
        refined=tuple(filter_to_ground_truth(single_refined, scan.ground_truth.keys)),
        ground_truth=scan.ground_truth.keys,
    )
    return RefinedViews(scan=scan, refined=tuple(single_refined), sets=sets)


def case_inputs(
    views: RefinedViews,
    cases: Sequence[int],
    refiner: Refiner,
    config: GenerationConfig,
    object_id: str,
    rotation: int,
) -> dict[int, tuple[PackedKeys, PackedKeys]]:
    """(P(O_S), keys(O_S)) for each case S: the one place a planner's input is built.

    A single view's input is its refinement from `refine_views`; a multi-view case refines the
    combined observation of its views. Generation and `datagen evaluate` both call this, so what a
    network is trained on and what it is tested on cannot drift apart.
    """
    singles = views.scan.observations
    inputs: dict[int, tuple[PackedKeys, PackedKeys]] = {}
    for case in cases:
        if case.bit_count() == 1:
            view = case.bit_length() - 1
            inputs[case] = (views.refined[view], singles[view].keys)
    multi = sorted({c for c in cases if c.bit_count() > 1}, key=lambda c: (c.bit_count(), c))
    combined = [Observation.combine([singles[v] for v in _views(c)]) for c in multi]
    for case, observation, points in zip(
        multi, combined, _refine(refiner, combined, config, object_id, rotation), strict=True
    ):
        inputs[case] = (points, observation.keys)
    return inputs


def run_task(
    prepared: PreparedObject,
    rotation: int,
    config: GenerationConfig,
    view_space: ViewSpace,
    refiner: Refiner,
    threads: int = 1,
    clock: StepClock | None = None,
) -> TaskResult:
    """Every sample of task (object, rotation), in memory; ``clock`` (a new one by default) gets
    each step's time (`schemas.index.TASK_STEPS` from ground_truth to labels)."""
    clock = StepClock() if clock is None else clock
    spec = prepared.spec
    task_id = spec.task_id(rotation)
    scan = scan_task(prepared, rotation, config, view_space, clock)

    with clock.step("refine_views"):
        views = refine_views(scan, refiner, config, spec.object_id, rotation)
    sets = views.sets
    with clock.step("cases"):
        cases = long_tail_cases(sets.visible, stream(config.seed, spec.object_id, rotation, Purpose.CASES))
    with clock.step("refine_cases"):
        inputs = case_inputs(views, cases, refiner, config, spec.object_id, rotation)

    labelled = label_task(sets, cases, config, threads, clock)
    with clock.step("next_view"):
        views_of_task = next_view_labels(sets, labelled, view_space.positions, config)
    with clock.step("labels"):
        samples, dropped = labelled_samples(task_id, cases, labelled, inputs, config, views_of_task.gains)
    timings = {
        "scan": clock.wall_of("ground_truth", "imaging"),
        "refine": clock.wall_of("refine_views", "cases", "refine_cases"),
        "label": clock.wall_of("coverage", "labels", "next_view"),
    }
    return TaskResult(
        task_id=task_id,
        object_id=spec.object_id,
        object_name=spec.name,
        rotation=rotation,
        sets=sets,
        cases=tuple(cases),
        samples=tuple(samples),
        failures=tuple(labelled.failures),
        dropped_empty=dropped,
        metadata=task_metadata(config, refiner),
        cover_rows=labelled.cover.minimal,
        seconds=timings,
        grids=views_of_task.grids,
        visible_size=views_of_task.gains.visible.total,
    )


@dataclass(frozen=True)
class TaskLabels:
    """P_full's coverage at one alpha, its set-cover rows, and every case's label under the config's
    objective."""

    coverage: Coverage
    cover: TaskCover
    """The paper's set-cover rows of P_full (a shard's ``cover_rows``, whatever the objective)."""
    labels: dict[int, CoverResult]
    failures: list[CaseFailure]


def label_task(
    sets: TaskSets, cases: Sequence[int], config: GenerationConfig, threads: int = 1, clock: StepClock | None = None
) -> TaskLabels:
    """P_full, coverage and each case's exact label (with the sets as good as it) for the config's
    objective (`datagen.pipeline.objectives`), from the stored V_i and P_i alone: what generation and
    `relabel` share; ``clock`` times coverage and labels."""
    with timed(clock, "coverage"):
        coverage = coverage_table(sets.refined, config.alpha)
    with timed(clock, "labels"):
        labeller = task_labeller(sets.visible, coverage, config)
        cover = labeller if isinstance(labeller, TaskCover) else cover_solver(coverage.masks, config)
        labels, failures = label_cases(labeller, cases, threads)
    return TaskLabels(coverage, cover, labels, failures)


@dataclass(frozen=True)
class NextViewLabels:
    """What the next-best-view families train on, per task: the counts every case's gains come from
    and each view's cells of the occupancy grid."""

    gains: TaskGains
    grids: ViewGrids


def next_view_labels(
    sets: TaskSets, labelled: TaskLabels, positions: npt.NDArray[np.float64], config: GenerationConfig
) -> NextViewLabels:
    """The next-view labels of a task from its stored sets and the view positions alone: what
    generation, `relabel` and `datagen shards validate --all` share (docs/pipeline.md section 8)."""
    return NextViewLabels(
        gains=TaskGains.of(sets.visible, labelled.coverage.masks),
        grids=view_grids(sets.visible, sets.ground_truth, positions, config.voxel_size, config.grid_offset),
    )


def labelled_samples(
    task_id: str,
    cases: Sequence[int],
    labelled: TaskLabels,
    inputs: Mapping[int, tuple[PackedKeys, PackedKeys]],
    config: GenerationConfig,
    gains: TaskGains | None = None,
) -> tuple[list[Sample], int]:
    """The task's samples in case order (cases without a label skipped) and how many empty
    labels ``empty_labels = "drop"`` dropped; ``inputs`` maps a case to (P(O_S), keys(O_S)); with
    ``gains``, each sample carries its next-view labels."""
    samples, dropped = [], 0
    for case in cases:
        cover = labelled.labels.get(case)
        if cover is None:
            continue
        empty = cover.status == "empty"
        if empty and config.empty_labels == "drop":
            dropped += 1
            continue
        points, observed = inputs[case]
        samples.append(
            Sample(
                sample_id=sample_id(task_id, case),
                case=case,
                label=cover.label,
                points=points,
                observed=observed,
                full_size=len(labelled.coverage),
                universe_size=cover.rows_before,
                cover=cover,
                empty_label=empty,
                gains=None if gains is None else gains.case(case),
            )
        )
    return samples, dropped


def task_metadata(config: GenerationConfig, refiner: Refiner) -> dict[str, object]:
    return {
        "refiner": refiner.name,
        "weights_id": refiner.weights_id,
        "device": str(getattr(refiner, "device", "cpu")),
        "seed": config.seed,
        "config_hash": config.config_hash(),
        "schema_version": SCHEMA_VERSION,
    }


def label_cases(
    solver: CaseLabeller, cases: Sequence[int], threads: int = 1
) -> tuple[dict[int, CoverResult], list[CaseFailure]]:
    """Each case's exact label; a case the solver cannot label is a failure."""
    labels: dict[int, CoverResult] = {}
    failures: list[CaseFailure] = []
    for case in cases:
        try:
            labels[case] = solver.label(case, threads)
        except LabelError as exc:  # past a work budget: the same on every machine, recorded in the shard
            failures.append(CaseFailure(case=case, message=str(exc)))
        except SolverTimeLimit as exc:  # the clock: fail the task (run again), never leave the case out
            raise SolverTimeLimit(f"case {case:016x} (views {', '.join(map(str, _views(case)))}): {exc}") from None
    return labels, failures


def _refine(
    refiner: Refiner,
    observations: Sequence[Observation],
    config: GenerationConfig,
    object_id: str,
    rotation: int,
) -> list[PackedKeys]:
    requests = [RefineRequest(o, config.seed, object_id, rotation) for o in observations]
    refinements = refiner.refine(requests)
    return [refined_keys(o, r) for o, r in zip(observations, refinements, strict=True)]


def _views(case: int) -> list[int]:
    return [v for v in range(case.bit_length()) if case >> v & 1]
