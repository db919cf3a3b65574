"""Relabel a dataset for another alpha, tie-break or label objective from its stored sets (docs/pipeline.md
section 8).

A shard keeps each view's P_i, so P_full, the coverage and every label of its stored cases can be
computed again without imaging or refining anything: the samples' points and observed sets are
carried over unchanged and only the labels (and their solver records) are new. The result is a new
dataset with its own config (the source's, alpha and tie-break as asked) and config hash, written task by task
through the same commit protocol as the engine, with the source's failure records carried over.
"""

from __future__ import annotations

import importlib.metadata
import platform
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from datagen.engine.parallel import run_each
from datagen.engine.shard_payload import task_payload
from datagen.errors import ConfigError, OutputError
from datagen.pipeline.keys import pack_keys
from datagen.pipeline.setcover import TIE_BREAKS
from datagen.pipeline.task import TaskResult, TaskSets, label_task, labelled_samples, next_view_labels
from schemas.config import GenerationConfig, MissingConfigFile
from schemas.dataset import DatasetInfo
from schemas.index import CommitRecord
from schemas.objectives import OBJECTIVES
from schemas.shard import GT_KEYS, MASKS, VIEW_STATE_COLUMN, keys_array, offsets_array
from schemas.version import SCHEMA_VERSION
from storage import (
    Location,
    ShardReader,
    StorageError,
    check_store,
    committed_tasks,
    finalise,
    holds_dataset,
    init_dataset,
    open_location,
    read_failures,
    read_info,
    write_failure,
    write_task,
)
from storage.dataset import task_records

TASK_METADATA = ("refiner", "weights_id", "device", "seed", "schema_version")
"""Per-task metadata carried over from the source shard (the config hash is the new one)."""


@dataclass(frozen=True)
class RelabelProgress:
    tasks_done: int
    tasks_total: int
    samples: int
    """Samples written so far."""
    task_id: str
    """The task just written."""


@dataclass(frozen=True)
class RelabelSummary:
    source: str
    out: str
    source_alpha: int
    alpha: int
    source_tie_break: str
    tie_break: str
    source_objective: str
    objective: str
    """The label objective with its parameter, e.g. ``max_coverage (budget 2)``."""
    source_config_hash: str
    config_hash: str
    tasks: int
    samples: int
    dropped_empty: int
    """Samples whose U became empty under ``empty_labels = 'drop'``."""
    failed_cases: int
    """Cases whose label could not be proven optimal (not written; named in the shard attributes)."""
    failures: int
    """Failure records carried over from the source."""
    seconds: float
    kept: int = 0
    """Tasks a stopped relabel into the same ``out`` had already committed: kept, not relabelled again."""

    @property
    def labels_per_second(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else float("inf")


def relabel_dataset(
    url: str,
    alpha: int | None,
    out_url: str,
    storage_options: dict[str, Any] | None = None,
    progress: Callable[[RelabelProgress], None] | None = None,
    tie_break: str | None = None,
    objective: str | None = None,
    budget: int | None = None,
    tau: float | None = None,
    workers: int = 1,
    address: str | None = None,
) -> RelabelSummary:
    """Write a new dataset at ``out_url`` labelling every committed task of ``url`` for ``alpha``,
    ``tie_break`` and the label ``objective`` with its ``budget`` or ``tau`` (None keeps the source's).

    Tasks are relabelled and committed one by one here, or side by side on Ray (`datagen.engine.parallel`):
    on the cluster at ``address``, or on a local Ray of ``workers`` CPUs."""
    started = time.perf_counter()
    source = open_location(url, storage_options)
    check_store(source)
    info = read_info(source)
    alpha = info.config.alpha if alpha is None else alpha
    changes = {"label_objective": objective, "label_budget": budget, "label_tau": tau}
    config = _with_labels(
        info.config,
        alpha,
        tie_break or info.config.label_tie_break,
        {k: v for k, v in changes.items() if v is not None},
    )
    target = open_location(out_url, storage_options)
    check_store(target)
    new_info = DatasetInfo(
        schema_version=SCHEMA_VERSION,
        config=config,
        config_hash=_config_hash(config),
        view_positions=info.view_positions,
        versions=_versions(),
        created=datetime.now(UTC).isoformat(timespec="seconds"),
    )
    kept = _resumed_tasks(target, new_info, out_url)
    if not holds_dataset(target):
        init_dataset(target, new_info)
    failures = read_failures(source)
    for failure in sorted(failures, key=lambda f: f.task_id):
        write_failure(target, failure)
    records = task_records(source)
    todo = [record for record in records.records if record.task_id not in kept]
    samples = dropped = failed = 0
    positions = np.asarray(info.view_positions)
    hashes = (new_info.config_hash, info.config_hash)
    calls = (
        (url, out_url, storage_options, record, records.spans.get(record.shard), config, *hashes, positions)
        for record in todo
    )
    for done, outcome in enumerate(run_each(relabel_and_commit, calls, workers, address), start=1):
        samples += outcome.samples
        dropped += outcome.dropped_empty
        failed += outcome.failed_cases
        if progress:
            progress(RelabelProgress(len(kept) + done, len(records.records), samples, outcome.task_id))
    finalise(target)
    return RelabelSummary(
        source=url,
        out=out_url,
        source_alpha=info.config.alpha,
        alpha=alpha,
        source_tie_break=info.config.label_tie_break,
        tie_break=config.label_tie_break,
        source_objective=info.config.objective_text(),
        objective=config.objective_text(),
        source_config_hash=info.config_hash,
        config_hash=new_info.config_hash,
        tasks=len(records.records),
        samples=samples,
        dropped_empty=dropped,
        failed_cases=failed,
        failures=len(failures),
        seconds=time.perf_counter() - started,
        kept=len(kept),
    )


@dataclass(frozen=True)
class TaskOutcome:
    """What relabelling one task wrote (all a parallel run sends back)."""

    task_id: str
    samples: int
    dropped_empty: int
    failed_cases: int


def relabel_and_commit(
    url: str,
    out_url: str,
    storage_options: dict[str, Any] | None,
    record: CommitRecord,
    span: tuple[str, int, int] | None,
    config: GenerationConfig,
    config_hash: str,
    source_hash: str,
    positions: npt.NDArray[np.float64],
) -> TaskOutcome:
    """Relabel one task of the dataset at ``url`` and commit it to ``out_url`` (here or in a Ray worker:
    it opens both stores itself)."""
    source, target = open_location(url, storage_options), open_location(out_url, storage_options)
    result = relabel_task(source, record, config, config_hash, source_hash, positions, span)
    write_task(target, task_payload(result, config), f"relabel-{uuid.uuid4().hex[:12]}")
    return TaskOutcome(record.task_id, len(result.samples), result.dropped_empty, len(result.failures))


def relabel_task(
    source: Location,
    record: CommitRecord,
    config: GenerationConfig,
    config_hash: str,
    source_hash: str,
    positions: npt.NDArray[np.float64],
    span: tuple[str, int, int] | None = None,
) -> TaskResult:
    """One committed task of the source, its stored cases labelled for ``config.alpha``, with the
    next-view labels computed from its visibility sets and the view ``positions`` (so a dataset of an
    older schema version gains them).

    Only the cases the source stored can be relabelled: a case the source dropped (empty label) or
    failed to label has no stored points.
    """
    started = time.perf_counter()
    shard = ShardReader(source, record.shard, span=span)
    attributes = shard.attributes
    num_views = attributes.num_views
    sets = TaskSets(
        visible=tuple(_key_sets(shard, "visible", num_views)),
        refined=tuple(_key_sets(shard, "refined", num_views)),
        ground_truth=pack_keys(shard.array(GT_KEYS)),
    )
    masks = shard.array(MASKS)
    cases = [int(c) for c in masks[:, VIEW_STATE_COLUMN]]
    labelled = label_task(sets, cases, config)
    views = next_view_labels(sets, labelled, positions, config)
    stored = zip(_key_sets(shard, "points", len(cases)), _key_sets(shard, "observed", len(cases)), strict=True)
    samples, dropped = labelled_samples(
        attributes.task_id, cases, labelled, dict(zip(cases, stored, strict=True)), config, views.gains
    )
    source_meta = attributes.metadata
    metadata: dict[str, object] = {name: source_meta[name] for name in TASK_METADATA if name in source_meta}
    metadata["config_hash"] = config_hash
    metadata["schema_version"] = SCHEMA_VERSION
    metadata["relabelled_from"] = {
        "config_hash": source_hash,
        "attempt_id": attributes.attempt_id,
        "cases": source_meta.get("cases"),
    }
    return TaskResult(
        task_id=attributes.task_id,
        object_id=attributes.object_id,
        object_name=attributes.object_name,
        rotation=attributes.rotation,
        sets=sets,
        cases=tuple(cases),
        samples=tuple(samples),
        failures=tuple(labelled.failures),
        dropped_empty=dropped,
        metadata=metadata,
        cover_rows=labelled.cover.minimal,
        seconds={"label": time.perf_counter() - started},
        grids=views.grids,
        visible_size=views.gains.visible.total,
    )


def _key_sets(shard: ShardReader, name: str, count: int) -> list[npt.NDArray[np.int64]]:
    """A stored per-sample or per-view key set family as packed keys."""
    keys, offsets = shard.array(keys_array(name)), shard.array(offsets_array(name))
    if offsets.shape != (count + 1,):
        raise StorageError(
            f"{shard.relative}: {offsets_array(name)} has {offsets.shape[0]} entries, expected {count + 1}; "
            "run 'datagen shards validate' on the source"
        )
    packed = pack_keys(keys)
    return [packed[offsets[i] : offsets[i + 1]] for i in range(count)]


OPTION_OF_FIELD = {
    "alpha": "--alpha",
    "label_tie_break": "--tie-break",
    "label_objective": "--objective",
    "label_budget": "--budget",
    "label_tau": "--tau",
}


def _with_labels(
    config: GenerationConfig, alpha: int, tie_break: str, changes: dict[str, object] | None = None
) -> GenerationConfig:
    if not 1 <= alpha <= config.num_views:
        raise ConfigError(
            f"--alpha {alpha} is outside 1..{config.num_views} (the dataset has {config.num_views} views)"
        )
    if tie_break not in TIE_BREAKS:
        raise ConfigError(f"--tie-break {tie_break!r} is not one of {', '.join(TIE_BREAKS)}")
    objective = (changes or {}).get("label_objective")
    if objective is not None and objective not in OBJECTIVES:
        raise ConfigError(f"--objective {objective!r} is not one of {', '.join(OBJECTIVES)}")
    update = {"alpha": alpha, "label_tie_break": tie_break, **(changes or {})}
    try:
        return GenerationConfig.model_validate({**config.model_dump(), **update})
    except ValidationError as exc:
        first = exc.errors()[0]
        if not first["loc"]:  # a rule between fields: its message names them
            raise ConfigError(str(first["msg"]).removeprefix("Value error, ")) from None
        field = str(first["loc"][0])
        option = OPTION_OF_FIELD.get(field, "--alpha")
        raise ConfigError(f"{option} {update.get(field, alpha)}: {first['msg']}") from None


def _config_hash(config: GenerationConfig) -> str:
    try:
        return config.config_hash()
    except (FileNotFoundError, MissingConfigFile) as exc:
        raise ConfigError(
            f"the source config names {exc.filename}, which is not here; it is hashed into the new config"
        ) from None


def _resumed_tasks(target: Location, info: DatasetInfo, out_url: str) -> set[str]:
    """The tasks a stopped relabel of the same source and settings already committed to ``target``
    (none for an empty one); another dataset there is refused, never mixed with."""
    if not holds_dataset(target):
        return set()
    there = read_info(target)
    if there.config_hash != info.config_hash:
        raise OutputError(
            f"{out_url}: already holds another dataset (config {there.config_hash[:12]}, this relabel makes "
            f"{info.config_hash[:12]}); give an empty --out, or the same one to finish a stopped relabel"
        )
    return {record.task_id for record in committed_tasks(target)}


def _versions() -> dict[str, str]:
    """The software that writes the new labels."""
    versions = {"python": platform.python_version(), "numpy": np.__version__}
    for package in ("datagen", "highspy", "zarr", "pyarrow"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            continue
    return versions
