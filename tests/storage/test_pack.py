"""A dataset at scale: a handful of files a task as written (version 5: each task's group one ZIP), and
a finished dataset packed into a few large tar files with one manifest (`storage.dataset.pack`), read by our
readers exactly as the original and by the standard tools as they are: zarr's own ``ZipStore`` for a
task's group, and the `webdataset` loader for the packs."""

from __future__ import annotations

import os
import tarfile
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
import zarr
import zarr.storage
from support import storage as fx

from schemas.shard import array_names
from schemas.version import SCHEMA_VERSION
from storage import ShardReader, StorageError, committed_tasks, open_dataset, open_location
from storage.checks import validate
from storage.dataset import pack_dataset
from storage.shards import zip_entries

PACK_BYTES = 200_000
"""Small packs: each holds about one of the tests' tasks, so the dataset has several."""


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("pack") / "original"
    fx.build_dataset(str(root), finalise_index=True)
    return root


@pytest.fixture(scope="module")
def packed(original: Path) -> Path:
    out = original.with_name("packed")
    summary = pack_dataset(str(original), str(out), target_bytes=PACK_BYTES)
    assert (summary.tasks, summary.samples) == (2, fx.total_samples())
    return out


def files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def test_a_task_is_three_files_and_its_group_is_one_zip_zarr_opens(original: Path) -> None:
    tasks = fx.task_ids()
    per_task = [name for name in files(original) if any(task in name for task in tasks)]
    assert len(per_task) == 3 * len(tasks)  # shard, index fragment, commit record
    location = open_location(str(original))
    for record in committed_tasks(location):
        assert record.shard.endswith(".zarr.zip") and zipfile.is_zipfile(original / record.shard)
        ours = ShardReader(location, record.shard)
        store = zarr.storage.ZipStore(original / record.shard, mode="r")
        try:
            group = zarr.open_group(store, mode="r")
            assert dict(group.attrs) == ours.attributes.model_dump(mode="json")
            for name in array_names(SCHEMA_VERSION):
                np.testing.assert_array_equal(np.asarray(group[name][...]), ours.array(name), err_msg=name)
        finally:
            store.close()


def test_the_same_arrays_give_the_same_shard_bytes(tmp_path: Path, original: Path) -> None:
    again = fx.build_dataset(str(tmp_path / "again"), finalise_index=True)
    for record in committed_tasks(again):
        assert (tmp_path / "again" / record.shard).read_bytes() == (original / record.shard).read_bytes()


def test_a_packed_dataset_is_a_few_files_and_reads_as_the_original(original: Path, packed: Path) -> None:
    names = files(packed)
    packs = [name for name in names if name.startswith("packs/")]
    assert len(packs) >= 2 and all(name.endswith(".tar") for name in packs)
    assert len(names) == len(packs) + 4  # dataset.json, the manifest, one tasks and one samples table
    ours, theirs = open_dataset(str(packed)), open_dataset(str(original))
    assert len(ours) == len(theirs) == fx.total_samples()
    assert ours.column("sample_id").equals(theirs.column("sample_id"))
    for column in ("label", "view_state", "row", "attempt_id", "label_support"):
        assert ours.column(column).equals(theirs.column(column)), column
    for i in range(len(ours)):
        a, b = ours[i], theirs[i]
        for key in ("points", "observed", "label", "view_state", "covers"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert validate(str(packed), full=True) == []


def test_the_stream_reads_a_packed_dataset_as_the_original(original: Path, packed: Path) -> None:
    from storage.stream import ShardStream

    def batches(root: Path) -> list[np.ndarray]:
        stream = ShardStream(str(root), num_points=128, batch_size=16, shuffle_buffer=64, seed=3)
        return [batch.points.numpy() for batch in stream.loader()]

    for ours, theirs in zip(batches(packed), batches(original), strict=True):
        np.testing.assert_array_equal(ours, theirs)


def test_webdataset_reads_the_packs_and_zarr_each_task(original: Path, packed: Path) -> None:
    import webdataset

    urls = sorted(str(p) for p in (packed / "packs").glob("*.tar"))
    found = list(webdataset.WebDataset(urls, shardshuffle=False))
    assert [sample["__key__"] for sample in found] == sorted(fx.task_ids())
    location = open_location(str(original))
    records = {r.task_id: r for r in committed_tasks(location)}
    for sample in found:
        assert set(sample) >= {"zarr.zip", "index.parquet"}
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "task.zarr.zip"
            path.write_bytes(sample["zarr.zip"])
            store = zarr.storage.ZipStore(path, mode="r")
            try:
                masks = np.asarray(zarr.open_group(store, mode="r")["masks"][...])
            finally:
                store.close()
        reference = ShardReader(location, records[sample["__key__"]].shard).array("masks")
        np.testing.assert_array_equal(masks, reference)


def test_packing_refuses_what_it_cannot_pack(original: Path, packed: Path, tmp_path: Path) -> None:
    unfinished = fx.build_dataset(str(tmp_path / "unfinished"))
    older = fx.build_dataset(str(tmp_path / "older"), schema_version=4, finalise_index=True)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "dataset.json").write_text("{}")
    cases = [
        (unfinished.url, str(tmp_path / "a"), "no finalised index"),
        (older.url, str(tmp_path / "b"), "relabel"),
        (str(packed), str(tmp_path / "c"), "already packed"),
        (str(original), str(tmp_path / "full"), "already holds a dataset"),
    ]
    for source, out, says in cases:
        with pytest.raises(StorageError, match=says) as caught:
            pack_dataset(source, out)
        assert "\n" not in str(caught.value)


def test_a_damaged_pack_is_named(packed: Path, tmp_path: Path) -> None:
    damaged = fx.copy_dataset(packed, tmp_path / "damaged")
    pack = sorted((damaged / "packs").glob("*.tar"))[0]
    with tarfile.open(pack) as archive:
        first = archive.getmembers()[0]
    data = bytearray(pack.read_bytes())
    shard = memoryview(bytes(data[first.offset_data : first.offset_data + first.size]))
    start, size = zip_entries(shard)["masks/c/0/0"]
    data[first.offset_data + start + size // 2] ^= 0xFF  # the first task's masks
    pack.write_bytes(bytes(data))
    dataset = open_dataset(str(damaged))
    with pytest.raises(StorageError) as caught:
        for i in range(len(dataset)):
            dataset[i]
    assert "packs/pack-00000.tar/" in str(caught.value) and "\n" not in str(caught.value)
    assert [line for line in validate(str(damaged), full=True) if "packs/pack-00000.tar/" in line]
    os.truncate(pack, first.offset_data + 10)
    assert [line for line in validate(str(damaged), full=True) if "packs/pack-00000.tar/" in line]
