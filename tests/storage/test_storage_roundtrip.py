"""Round trip: what `run_task` produced is what a reader gets back, bit for bit, on the local disk
and on fsspec's memory filesystem; plus filters, splits, shuffles, finalise and error messages."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import fsspec
import numpy as np
import pyarrow as pa
import pytest
from support import storage as fx

from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.index import INDEX_SCHEMA, FailureRecord
from schemas.shard import array_names, point_order
from schemas.version import SCHEMA_VERSION
from storage.dataset import (
    ADDING_FILE,
    MANIFEST_FILE,
    committed_tasks,
    finalise,
    fragment_path,
    init_dataset,
    load_index,
    mark_adding,
    read_commit,
    read_failures,
    read_info,
    read_manifest,
    shard_path,
    write_failure,
    write_task,
)
from storage.readers import Dataset, open_dataset
from storage.shards import ShardReader
from storage.store import StorageError, open_location


@pytest.fixture(scope="module")
def local_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    url = str(tmp_path_factory.mktemp("roundtrip") / "ds")
    fx.build_dataset(url)
    return url


@pytest.fixture(scope="module")
def memory_url() -> Iterator[str]:
    name = f"datagen-test-{uuid.uuid4().hex}"
    url = f"memory://{name}"
    fx.build_dataset(url)
    yield url
    fsspec.filesystem("memory").rm(f"/{name}", recursive=True)


@pytest.fixture(params=["local", "memory"])
def dataset_url(request: pytest.FixtureRequest) -> str:
    return str(request.getfixturevalue(f"{request.param}_url"))


def positions(ds: Dataset) -> dict[str, int]:
    ids = ds.index.column("sample_id").to_pylist()
    assert len(ids) == len(set(ids))
    return {sample_id: i for i, sample_id in enumerate(ids)}


def bits(mask: int, width: int) -> np.ndarray:
    return np.array([(mask >> v) & 1 == 1 for v in range(width)])


def test_samples_read_back_bit_identical(dataset_url: str) -> None:
    cfg = fx.config()
    ds = open_dataset(dataset_url)
    assert len(ds) == fx.total_samples() > 0
    where = positions(ds)
    for result in fx.task_results():
        for s in result.samples:
            i = where[s.sample_id]
            # Version 4 stores the refined cloud in its seeded order (tests/storage/test_point_order.py).
            order = point_order(cfg.seed, result.object_id, result.rotation, s.case, s.points.size)
            for source, keys_as_stored in (
                ("points", fx.int16_keys(s.points)[order]),
                ("observed", fx.int16_keys(s.observed)),
            ):
                keys = ds.keys(i, source)
                assert keys.dtype == np.int16
                np.testing.assert_array_equal(keys, keys_as_stored)
            assert ds.masks(i) == (s.case, s.label)
            item = ds[i]
            assert item["sample_id"] == s.sample_id
            assert item["points"].dtype == np.float32
            np.testing.assert_array_equal(item["points"], s.point_centres(cfg)[order])
            expected_observed = ds.centres(fx.int16_keys(s.observed))
            np.testing.assert_array_equal(item["observed"], expected_observed)
            np.testing.assert_array_equal(item["view_state"], bits(s.case, cfg.num_views))
            np.testing.assert_array_equal(item["label"], bits(s.label, cfg.num_views))
    assert ds[-1]["sample_id"] == ds.index.column("sample_id")[len(ds) - 1].as_py()
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_task_sets_and_arrays_read_back_bit_identical(dataset_url: str) -> None:
    location = open_location(dataset_url)
    commits = {r.task_id: r for r in committed_tasks(location)}
    assert len(commits) == len(fx.task_results())
    for result, payload in zip(fx.task_results(), fx.payloads(), strict=True):
        record = commits[result.task_id]
        assert record.attempt_id == fx.ATTEMPT
        assert record.shard == shard_path(result.task_id, fx.ATTEMPT)
        assert record.index_fragment == fragment_path(result.task_id, fx.ATTEMPT)
        assert record.num_samples == len(result.samples)
        reader = ShardReader(location, record.shard)
        assert reader.attributes == payload.attributes.model_copy(update={"attempt_id": fx.ATTEMPT})
        assert reader.array_names() == array_names()
        for name in array_names():
            got, expected = reader.array(name), payload.arrays[name]
            assert got.dtype == expected.dtype and got.shape == expected.shape, name
            np.testing.assert_array_equal(got, expected)
        for view in range(fx.config().num_views):
            np.testing.assert_array_equal(reader.key_set("visible", view), fx.int16_keys(result.sets.visible[view]))
            np.testing.assert_array_equal(reader.key_set("refined", view), fx.int16_keys(result.sets.refined[view]))
        np.testing.assert_array_equal(reader.array("gt_keys"), fx.int16_keys(result.sets.ground_truth))


def test_index_columns_equal_the_payload(dataset_url: str) -> None:
    ds = open_dataset(dataset_url)
    assert ds.index.schema.remove_metadata() == INDEX_SCHEMA
    task_ids = ds.index.column("task_id").to_pylist()
    for payload in fx.payloads():
        task_id = payload.attributes.task_id
        rows = [i for i, t in enumerate(task_ids) if t == task_id]
        table = ds.index.take(pa.array(rows))
        for name, values in payload.index_rows.items():
            assert table.column(name).to_pylist() == values, name
        count = payload.attributes.num_samples
        assert table.column("shard").to_pylist() == [shard_path(task_id, fx.ATTEMPT)] * count
        assert table.column("row").to_pylist() == list(range(count))
        assert table.column("attempt_id").to_pylist() == [fx.ATTEMPT] * count
        assert set(payload.index_rows) | {"shard", "row", "attempt_id"} == set(INDEX_SCHEMA.names)


def test_a_column_read_once_is_the_kept_one(dataset_url: str) -> None:
    """``values(name, keep=False)`` (a command reading a column of millions once) gives the kept column's
    values without keeping them; a column already kept is handed out as it is."""
    ds = open_dataset(dataset_url)
    once = ds.values("num_points", keep=False)
    assert "num_points" not in ds._columns
    kept = ds.values("num_points")
    np.testing.assert_array_equal(once, kept)
    assert once.dtype == kept.dtype and ds.values("num_points", keep=False) is kept


def test_dataset_info_round_trip(dataset_url: str) -> None:
    info = read_info(open_location(dataset_url))
    assert info == fx.dataset_info()
    assert open_dataset(dataset_url).num_views == fx.config().num_views == info.num_views


def test_filter(local_url: str) -> None:
    ds = open_dataset(local_url)
    names = ds.index.column("object_name").to_pylist()
    sizes = ds.index.column("case_size").to_pylist()
    capsule, cone = fx.task_results()
    by_name = ds.filter(objects="capsule")
    assert len(by_name) == names.count("capsule") == len(capsule.samples)
    assert set(by_name.index.column("object_name").to_pylist()) == {"capsule"}
    by_id = ds.filter(objects=[cone.object_id])
    assert by_id.index.column("sample_id").to_pylist() == [s.sample_id for s in cone.samples]
    assert len(ds.filter(objects=["capsule", cone.object_id])) == len(ds)
    assert len(ds.filter(objects="no-such-object")) == 0
    assert len(ds.filter(rotations=0)) == len(ds)
    assert len(ds.filter(rotations=[1, 2])) == 0
    for wanted in ([1], [2, 3]):
        picked = ds.filter(case_sizes=wanted)
        assert len(picked) == sum(s in wanted for s in sizes) > 0
        assert set(picked.index.column("case_size").to_pylist()) <= set(wanted)
    both = ds.filter(objects="cone", rotations=[0], case_sizes=2)
    expected = [s.sample_id for s in cone.samples if s.case.bit_count() == 2]
    assert both.index.column("sample_id").to_pylist() == expected
    # A filtered dataset still reads the right samples.
    i = positions(ds)[expected[0]]
    np.testing.assert_array_equal(both[0]["points"], ds[i]["points"])
    assert len(ds.filter(case_sizes=7).filter(objects="capsule")) == len(ds.filter(objects="capsule", case_sizes=7))


def test_split_by_object_and_deterministic(local_url: str) -> None:
    ds = open_dataset(local_url)
    for seed in range(4):
        train, val = ds.split(val=0.5, seed=seed)
        train_ids = set(train.index.column("sample_id").to_pylist())
        val_ids = set(val.index.column("sample_id").to_pylist())
        assert not train_ids & val_ids and len(train_ids) + len(val_ids) == len(ds)
        train_objects, val_objects = set(train.object_ids()), set(val.object_ids())
        assert not train_objects & val_objects
        assert len(train_objects) == len(val_objects) == 1  # 2 objects, half each
        for side, objects in ((train, train_objects), (val, val_objects)):
            assert len(side) == len(ds.filter(objects=sorted(objects)))
        again_train, again_val = ds.split(val=0.5, seed=seed)
        assert again_train.index.equals(train.index) and again_val.index.equals(val.index)
    everything, nothing = ds.split(val=0.0, seed=3)
    assert len(everything) == len(ds) and len(nothing) == 0
    nothing, everything = ds.split(val=1.0, seed=3)
    assert len(everything) == len(ds) and len(nothing) == 0
    with pytest.raises(ValueError):
        ds.split(val=1.5)


def test_shuffled_order(local_url: str) -> None:
    ds = open_dataset(local_url)
    n = len(ds)
    for mixed in (1000, 3, 1):
        first = ds.shuffled_order(seed=7, epoch=0, shards_mixed=mixed)
        assert first.dtype == np.int64
        assert sorted(first.tolist()) == list(range(n))
        np.testing.assert_array_equal(first, ds.shuffled_order(seed=7, epoch=0, shards_mixed=mixed))
        assert not np.array_equal(first, ds.shuffled_order(seed=7, epoch=1, shards_mixed=mixed))
        assert not np.array_equal(first, ds.shuffled_order(seed=8, epoch=0, shards_mixed=mixed))
        assert not np.array_equal(first, np.arange(n))
    ids = [s["sample_id"] for s in ds.iter_shuffled(seed=7, epoch=0)]
    all_ids = ds.index.column("sample_id").to_pylist()
    assert ids == [all_ids[i] for i in ds.shuffled_order(seed=7, epoch=0)]


@pytest.mark.parametrize("backend", ["local", "memory"])
def test_finalise_then_reopen_gives_the_same_index(backend: str, tmp_path: Path) -> None:
    name = f"datagen-test-{uuid.uuid4().hex}"
    url = str(tmp_path / "ds") if backend == "local" else f"memory://{name}"
    try:
        first, second = fx.payloads()
        location = fx.build_dataset(url, task_payloads=[first])
        before = open_dataset(url).index
        finalised = finalise(location)
        assert location.exists(MANIFEST_FILE) and read_manifest(location) == finalised.manifest
        assert (finalised.num_tasks, finalised.num_samples) == (1, len(before))
        assert load_index(location).equals(before)
        reopened = open_dataset(url)
        assert reopened.index.equals(before)
        assert reopened.index.schema.remove_metadata() == INDEX_SCHEMA
        np.testing.assert_array_equal(reopened[3]["points"], open_dataset(url)[3]["points"])
        # A task committed after finalise (a job adding: it says so first) shows up before the next one.
        mark_adding(location)
        write_task(location, second, "late")
        grown = open_dataset(url)
        assert len(grown) == fx.total_samples()
        assert set(grown.index.column("task_id").to_pylist()) == {first.attributes.task_id, second.attributes.task_id}
        assert grown.index.slice(0, len(before)).equals(before)
        appended = finalise(location)  # a second segment: the task committed since
        assert (appended.added_tasks, len(appended.manifest.segments)) == (1, 2)
        assert not location.exists(ADDING_FILE)  # every task is named again
        assert open_dataset(url).index.equals(grown.index)
        assert load_index(location).equals(grown.index)
    finally:
        if backend == "memory":
            fsspec.filesystem("memory").rm(f"/{name}", recursive=True)


def test_open_a_non_dataset_url_raises_storage_error(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    for url in (str(empty), str(tmp_path / "missing"), f"memory://datagen-test-{uuid.uuid4().hex}"):
        with pytest.raises(StorageError) as caught:
            open_dataset(url)
        message = str(caught.value)
        assert url in message and "not a datagen dataset" in message


def test_init_dataset_refuses_another_config(tmp_path: Path) -> None:
    location = open_location(str(tmp_path / "ds"))
    info = fx.dataset_info()
    assert init_dataset(location, info) == info
    assert init_dataset(location, info.model_copy(update={"created": "later"})) == info  # same config: reuse
    other_config = GenerationConfig(alpha=fx.config().alpha + 1)
    assert other_config.config_hash() != info.config_hash
    other = DatasetInfo(**{**info.model_dump(), "config": other_config, "config_hash": other_config.config_hash()})
    with pytest.raises(StorageError) as caught:
        init_dataset(location, other)
    message = str(caught.value)
    assert "another config" in message and info.config_hash[:12] in message and other.config_hash[:12] in message
    assert read_info(location) == info  # untouched


def test_failure_records_round_trip_and_a_later_success_clears_them(tmp_path: Path) -> None:
    payload = fx.payloads()[0]
    task_id = payload.attributes.task_id
    location = fx.build_dataset(str(tmp_path / "ds"), task_payloads=[])
    record = FailureRecord(
        schema_version=SCHEMA_VERSION, task_id=task_id, object_name="capsule", origin="objects.txt:1", message="boom"
    )
    write_failure(location, record)
    assert read_failures(location) == [record]
    assert open_dataset(location.url).failures() == [record]
    write_task(location, payload, "retry")
    assert read_commit(location, task_id) is not None
    assert read_failures(location) == []


def test_adding_to_a_dataset_of_another_poco_version_names_the_setting(tmp_path: Path) -> None:
    """A dataset made at poco_version 1 (every one before the field) and a job at the new default: one
    line that says which setting would add to it."""
    location = open_location(str(tmp_path / "ds"))
    made = GenerationConfig(poco_version=1)
    info = DatasetInfo(**{**fx.dataset_info().model_dump(), "config": made, "config_hash": made.config_hash()})
    init_dataset(location, info)
    now = GenerationConfig()
    job = DatasetInfo(**{**info.model_dump(), "config": now, "config_hash": now.config_hash()})
    with pytest.raises(StorageError, match=r"made with poco_version = 1, this job has 2: set it to add to it"):
        init_dataset(location, job)


def test_finalise_writes_a_damaged_or_withdrawn_manifest_again(tmp_path: Path) -> None:
    """A manifest that cannot be read, or that names a task whose record was withdrawn, is written
    again from the commit records (what `shards repair` and a resumed job's end rely on)."""
    from storage.checks import withdraw

    location = fx.build_dataset(str(tmp_path / "ds"), finalise_index=True)
    reference = open_dataset(str(tmp_path / "ds")).index
    (tmp_path / "ds" / MANIFEST_FILE).write_text("{not json")
    assert finalise(location).added_tasks == 2
    assert open_dataset(str(tmp_path / "ds")).index.equals(reference)
    first = sorted(fx.task_ids())[0]
    withdraw(location, [first])  # out of the manifest, then its records
    assert open_dataset(str(tmp_path / "ds")).column("task_id").to_pylist().count(first) == 0
    assert finalise(location).num_tasks == 1
