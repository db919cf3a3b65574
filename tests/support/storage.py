"""Helpers shared by the storage tests: small real datasets built from two built-in shapes.

The pipeline runs once per test process (`task_results` is cached), so every storage test reuses
the same `TaskResult`s and `ShardPayload`s; building a dataset from them only writes files.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import zarr
import zarr.storage

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.version import SCHEMA_VERSION
from storage.dataset import ShardPayload, finalise, init_dataset, write_task
from storage.shards import zip_bytes
from storage.store import Location, open_location

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


@contextlib.contextmanager
def shard_group(path: Path, mode: str = "r") -> Iterator[zarr.Group]:
    """The zarr group of a shard as zarr itself opens it (the tests' independent reader): a folder group
    (layouts 1-4) directly, a ZIP (layout 5) through zarr's ``ZipStore``. A ZIP opened for writing is
    extracted, edited as a folder and zipped again as the writer zips (`storage.shards.zip_bytes`)
    when the block ends."""
    if not path.name.endswith(".zip"):
        yield zarr.open_group(str(path), mode=mode)  # type: ignore[arg-type]
        return
    if mode == "r":
        store = zarr.storage.ZipStore(path, mode="r")
        try:
            yield zarr.open_group(store, mode="r")
        finally:
            store.close()
        return
    with tempfile.TemporaryDirectory() as folder:
        with zipfile.ZipFile(path) as archive:
            archive.extractall(folder)
        yield zarr.open_group(folder, mode=mode)  # type: ignore[arg-type]
        files = sorted(p for p in Path(folder).rglob("*") if p.is_file())
        path.write_bytes(zip_bytes({p.relative_to(folder).as_posix(): p.read_bytes() for p in files}))


def stored_array(path: Path, name: str) -> npt.NDArray[Any]:
    """Array ``name`` of the shard at ``path``, read by zarr (`shard_group`)."""
    with shard_group(path) as group:
        return np.asarray(group[name][...])


def edit_array(path: Path, name: str, change: Any) -> None:
    """Replace array ``name`` of the shard at ``path`` by ``change(its values)`` (a damage of content)."""
    with shard_group(path, mode="r+") as group:
        values = change(np.asarray(group[name][...]).copy())
        del group[name]
        group.create_array(name, data=values)


def zip_members(data: bytes) -> dict[str, bytes]:
    """A shard ZIP's members by name."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {name: archive.read(name) for name in archive.namelist()}


def without_member(data: bytes, member: str) -> bytes:
    """A shard ZIP's bytes written again without ``member`` (a member lost)."""
    return zip_bytes({name: value for name, value in zip_members(data).items() if name != member})


def with_member_cut(data: bytes, member: str, keep: float = 0.5) -> bytes:
    """A shard ZIP's bytes written again with ``member`` cut to ``keep`` of its bytes (0: emptied; the
    ZIP itself stays sound)."""
    members = zip_members(data)
    members[member] = members[member][: int(len(members[member]) * keep)]
    return zip_bytes(members)


def zip_without(path: Path, member: str) -> None:
    """The shard's ZIP written again without ``member`` (a member lost)."""
    path.write_bytes(without_member(path.read_bytes(), member))


def truncate_member(path: Path, member: str, keep: float = 0.5) -> None:
    """The shard's ZIP written again with ``member`` cut to ``keep`` of its bytes."""
    path.write_bytes(with_member_cut(path.read_bytes(), member, keep))


def corrupt_member(path: Path, member: str) -> None:
    """Flip a byte in the middle of ``member``'s stored bytes (the ZIP's own directory stays intact)."""
    from storage.shards import zip_entries

    data = bytearray(path.read_bytes())
    start, size = zip_entries(memoryview(bytes(data)))[member]
    data[start + size // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def finalise_as_before(location: Location) -> None:
    """The finalised index an earlier datagen wrote (before the manifest): every committed fragment
    merged into ``index.parquet``, then ``index.json`` = {task id: attempt id} of the commits it covers;
    a dataset finalised so must still read as it did."""
    import json

    from storage.dataset import INDEX_COVERAGE_FILE, INDEX_FILE, committed_tasks, merge_fragments
    from storage.store import parquet_bytes

    commits = committed_tasks(location)
    location.remove("index", recursive=True)
    location.write_atomic(INDEX_FILE, parquet_bytes(merge_fragments(location, commits)))
    coverage = {r.task_id: r.attempt_id for r in commits}
    location.write_atomic(INDEX_COVERAGE_FILE, json.dumps(coverage, sort_keys=True).encode())


def samples_table(root: Path) -> Path:
    """The finalised index's samples table of a dataset finalised once (the manifest's one segment)."""
    import json

    (only,) = json.loads((root / "index" / "manifest.json").read_text())["segments"]
    return root / only["samples"]
