"""Helpers shared by the storage tests: small real datasets built from two built-in shapes.

The pipeline runs once per test process (`task_results` is cached), so every storage test reuses
the same `TaskResult`s and `ShardPayload`s; building a dataset from them only writes files.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.version import SCHEMA_VERSION
from storage.dataset_info import init_dataset
from storage.location import Location, open_location
from storage.reader import finalise
from storage.writer import ShardPayload, write_task

OBJECTS = ("builtin:capsule", "builtin:cone")
ROTATION = 0
ATTEMPT = "a1"
CREATED = "2026-01-01T00:00:00"


@functools.cache
def config(**changes: object) -> GenerationConfig:
    """The tests' config (refiner none), with ``changes`` (e.g. another label objective)."""
    return GenerationConfig.model_validate({"refiner": "none", **changes})


@functools.cache
def _view_space():  # type: ignore[no-untyped-def]
    from datagen.pipeline.viewspace import build_view_space

    return build_view_space(config().view_space)


@functools.cache
def _specs() -> tuple:  # type: ignore[type-arg]
    from datagen.pipeline.objects.objects_file import read_objects_file

    with tempfile.TemporaryDirectory() as folder:
        objects_file = Path(folder) / "objects.txt"
        objects_file.write_text("".join(f"{source}\n" for source in OBJECTS))
        return tuple(read_objects_file(objects_file).objects)


def task_ids() -> list[str]:
    """The task ids of `OBJECTS` at rotation 0, in `OBJECTS` order (cheap: no pipeline run)."""
    return [spec.task_id(ROTATION) for spec in _specs()]


@functools.cache
def task_results(cfg: GenerationConfig | None = None) -> tuple:  # type: ignore[type-arg]
    """`run_task` for each of `OBJECTS` at rotation 0 (default: the tests' config), computed once per
    process and config."""
    from datagen.pipeline.objects.prepare import prepare_object
    from datagen.pipeline.refine import make_refiner
    from datagen.pipeline.task import run_task

    cfg = config() if cfg is None else cfg
    results = []
    for spec in _specs():
        prepared = prepare_object(spec, cfg)
        results.append(run_task(prepared, ROTATION, cfg, _view_space(), make_refiner(cfg)))
    return tuple(results)


@functools.cache
def payloads(schema_version: int = SCHEMA_VERSION, cfg: GenerationConfig | None = None) -> tuple[ShardPayload, ...]:
    """Every task's payload in layout ``schema_version`` (1: without the label ambiguity), generated
    under ``cfg`` (default: the tests' config)."""
    from datagen.engine.shard_payload import task_payload

    cfg = config() if cfg is None else cfg
    return tuple(task_payload(result, cfg, schema_version) for result in task_results(cfg))


@functools.cache
def small_payload(samples: int = 6) -> ShardPayload:
    """The first task with only its first ``samples`` samples (the per-task sets stay whole)."""
    from datagen.engine.shard_payload import task_payload

    result = task_results()[0]
    return task_payload(dataclasses.replace(result, samples=result.samples[:samples]), config())


def dataset_info(schema_version: int = SCHEMA_VERSION, cfg: GenerationConfig | None = None) -> DatasetInfo:
    cfg = config() if cfg is None else cfg
    return DatasetInfo(
        schema_version=schema_version,
        config=cfg,
        config_hash=cfg.config_hash(),
        view_positions=[tuple(p) for p in _view_space().positions.tolist()],
        versions={},
        created=CREATED,
    )


def build_dataset(
    url: str,
    task_payloads: Sequence[ShardPayload] | None = None,
    attempt_id: str = ATTEMPT,
    finalise_index: bool = False,
    schema_version: int = SCHEMA_VERSION,
    cfg: GenerationConfig | None = None,
) -> Location:
    """Initialise a dataset at ``url`` (layout ``schema_version``, generated under ``cfg``, default the
    tests' config) and commit each payload (default: every task, in that layout) with ``attempt_id``."""
    location = open_location(url)
    init_dataset(location, dataset_info(schema_version, cfg))
    for payload in payloads(schema_version, cfg) if task_payloads is None else task_payloads:
        write_task(location, payload, attempt_id)
    if finalise_index:
        finalise(location)
    return location


def finalised_dataset(factory: pytest.TempPathFactory, schema_version: int) -> Path:
    """A finalised dataset of every task in layout ``schema_version`` in a fresh folder of ``factory``:
    what a module-scoped fixture of one layout builds."""
    root = factory.mktemp(f"v{schema_version}") / "ds"
    build_dataset(str(root), finalise_index=True, schema_version=schema_version)
    return root


def build_many_tasks(url: str, copies: int) -> Location:
    """A finalised dataset of ``copies`` x `OBJECTS` tasks: each payload committed again under task
    ids ``<task id><copy>`` (index rows renamed to match), so the index is ``copies`` times larger."""
    location = open_location(url)
    init_dataset(location, dataset_info())
    for copy in range(copies):
        for payload in payloads():
            task_id = f"{payload.attributes.task_id}{copy:03d}"
            rows = dict(payload.index_rows)
            rows["task_id"] = [task_id] * payload.attributes.num_samples
            rows["sample_id"] = [f"{task_id}-{sample.rsplit('-', 1)[1]}" for sample in rows["sample_id"]]
            attributes = payload.attributes.model_copy(update={"task_id": task_id})
            write_task(location, dataclasses.replace(payload, attributes=attributes, index_rows=rows), ATTEMPT)
    finalise(location)
    return location


def copy_dataset(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def int16_keys(packed: npt.NDArray[np.int64]) -> npt.NDArray[np.int16]:
    """Packed pipeline keys as the (K, 3) int16 triples a shard stores."""
    from datagen.pipeline.keys import keys_to_int16, unpack_keys

    return keys_to_int16(unpack_keys(packed)).reshape(-1, 3)


def total_samples() -> int:
    return sum(p.attributes.num_samples for p in payloads())
